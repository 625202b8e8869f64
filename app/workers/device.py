"""One device inside a worker: reorder buffer, filter, zones, and the snapshot that resumes them."""

from __future__ import annotations

import json
import math
import zlib
from typing import Any

import msgspec

from app.core.identity import DeviceKey
from app.engine.samples import Batch, Estimate
from app.sites.assembly import LoadedSite
from app.workers.convert import Skipped, to_batch
from app.workers.messages import Position, Sample, ZoneEvent
from app.workers.trackers import (
    RADIO_KINDS,
    DeviceTracker,
    SiteEngines,
    choose_kind,
    make_tracker,
    radio_kind,
)
from app.workers.zones import ZoneTracker

CHOOSE_WITHIN_MS = 10_000
"""Measurement time a new device's samples may wait for one that can place it."""


SCAN_DELIVERY_MS = 4_000
"""How long before its delivery a WiFi reading may have been heard.

A phone reports a WiFi scan when it completes, with every access point
timed by when it was heard, seconds earlier on ILC site1's phones
(a client may send those last-seen times as ``t``); meanwhile its inertial
samples of those seconds have already gone out and been used. A WiFi
reading is therefore late only behind the WiFi already used, or this far
behind everything: dropping the rest as late cut every scan sent with
per-reading times in two."""


STORED_ONLY = ("odometry_x", "odometry_y")
"""Keys of a position message kept in the history but not sent to clients."""


def public(position: Position) -> Position:
    """Return a position message as clients get it (without what only the history keeps)."""
    return {k: v for k, v in position.items() if k not in STORED_ONLY}


def _odometry(estimate: Estimate) -> dict[str, float | None]:
    """Return the estimate's odometry (m) under the history's keys, null without one."""
    odo = estimate.odometry
    if odo is None:
        return {"odometry_x": None, "odometry_y": None}
    return {"odometry_x": round(float(odo[0]), 3), "odometry_y": round(float(odo[1]), 3)}


def late_before(kind: str, processed_t: int, processed_wifi_t: int = -1) -> int:
    """Return the time at or before which a sample of ``kind`` arrives too late to be used."""
    if kind == "wifi":
        return max(processed_wifi_t, processed_t - SCAN_DELIVERY_MS)
    return processed_t


def _places(batch: Batch) -> bool:
    """Return whether a batch holds samples that say where a device is."""
    return bool(len(batch.rssi) or len(batch.ranges) or len(batch.fixes) or len(batch.sightings))


_msgpack = msgspec.msgpack.Encoder()
"""Encodes a sample for its identity and a snapshot's reorder buffer."""


def _key(kind: str, sample: Sample) -> int:
    """Return the identity of a sample, to recognise the same sample delivered twice.

    The hash of the sample's msgpack bytes: cheaper than its ``repr``, and the
    bytes tell the same values apart (ints from floats, 0.0 from -0.0).
    """
    return hash((kind, _msgpack.encode(sample)))


def _buffered(stored: str | bytes) -> list[Any]:
    """Return a snapshot's reorder buffer as [t, kind, sample] items.

    msgpack bytes since they cost a tenth of JSON text to write (a worker
    snapshots every device every ``snapshot_every_ms``); snapshots holding the
    JSON text of earlier releases still resume.
    """
    if isinstance(stored, str):
        return json.loads(stored)
    return msgspec.msgpack.decode(stored) if stored else []


PERIOD_GAIN = 0.25
"""Weight of the newest gap between two batches' arrivals in a device's upload period."""

PERIOD_JUMP = 4.0
"""A gap counts for at most this many upload periods: a device that slows down for good
is followed within a few batches, one pause barely moves the period."""


class DeviceSession:
    """A device's live state: samples wait in a reorder window, then feed its filter.

    The filter is chosen when the first samples are released (``tracker`` is
    None until then), since what a device sends decides which filter fits.

    Samples are held until they are ``reorder_ms`` older (in measurement time)
    than the newest sample seen, so batches that overtake each other on the
    network are still used in time order. Older arrivals are counted late.

    The session reads no clock: its owner passes the wall time (``now``, epoch
    milliseconds) to the calls that need it. Zone events wait ``zone_dwell_ms``
    of measurement time on the new side of a zone's edge (``ZoneTracker``).

    ``consumed`` counts the batches this session took in and ``covered`` how
    many of them its last stored snapshot holds: a broker that acknowledges a
    batch only once it is covered re-delivers, after a crash, every batch whose
    samples the lost session held and no snapshot kept.
    """

    def __init__(
        self,
        *,
        device_id: str,
        engines: SiteEngines,
        now: int,
        zone_dwell_ms: int = 0,
        zone_exit_tolerance: float = 0.0,
    ) -> None:
        self.device_id = device_id
        self.engines = engines
        self.tracker: DeviceTracker | None = None
        self.processed_t = -1
        self.processed_wifi_t = -1
        self.max_t = -1
        self.zones = ZoneTracker(zone_dwell_ms)
        self.zone_exit_tolerance = zone_exit_tolerance
        """Multiple of a position's accuracy radius within which a position just outside a
        zone the device is in still counts as inside (the filter's error, not a step out)."""
        self.buffer: list[tuple[int, str, Sample]] = []
        self.seen: dict[int, int] = {}
        """The identity of each buffered sample, and its time."""
        self.snapshot_t = -1
        self.consumed = 0
        self.covered = 0
        self.last_seen = now
        self.arrived = -1
        self.period_ms = 0.0
        self.emitted_t = -1
        self.smoothed_t = -1
        self.unflushed = False
        self.kinds: set[str] = set()

    @property
    def key(self) -> DeviceKey:
        """Return the device's identity, (site id, device id)."""
        return (self.engines.site.site_id, self.device_id)

    @property
    def site(self) -> LoadedSite:
        """Return the site version the device is positioned on."""
        return self.engines.site

    @property
    def pending(self) -> bool:
        """Return whether samples wait in the buffer or the filter has unflushed input."""
        return bool(self.buffer) or self.unflushed

    # -- samples in, batches out -----------------------------------------------------

    def add(self, samples: dict[str, list[Sample]], *, now: int) -> tuple[int, int, int]:
        """Buffer a batch received at ``now``; return (accepted, late, duplicate) sample counts."""
        accepted = late = duplicate = 0
        for kind, items in samples.items():
            too_old = late_before(kind, self.processed_t, self.processed_wifi_t)
            for sample in items:
                t = sample["t"]
                if t <= too_old:
                    late += 1
                    continue
                key = _key(kind, sample)
                if key in self.seen:
                    duplicate += 1
                    continue
                self.seen[key] = t
                self.buffer.append((t, kind, sample))
                self.max_t = max(self.max_t, t)
                accepted += 1
        if self.arrived >= 0:
            # the upload period: the gaps between arrivals, smoothed, one long pause
            # (a device put away for a minute) counted as a few periods only
            gap = float(now - self.arrived)
            if self.period_ms:
                gap = min(gap, PERIOD_JUMP * self.period_ms)
                self.period_ms += PERIOD_GAIN * (gap - self.period_ms)
            else:
                self.period_ms = gap
        self.arrived = self.last_seen = now
        return accepted, late, duplicate

    def quiet_after_ms(self, flush_ms: float, periods: float) -> float:
        """Return the wall time (ms) of silence after which the device counts as quiet:
        ``flush_ms``, or ``periods`` of its upload period when that is longer."""
        return max(flush_ms, periods * self.period_ms)

    def take(self, *, reorder_ms: int, flush: bool) -> tuple[Batch | None, Skipped]:
        """Release what is older than the reorder window (all of it on flush) as engine arrays.

        Returns the batch (None when nothing is released) and what of it the
        engines do not use (``Skipped``). The first batch that can
        place the device (radio, ranges, fixes or sightings of the site's
        infrastructure) chooses its filter; inertial samples before it wait
        with it, up to ``CHOOSE_WITHIN_MS``, so a phone whose first upload
        holds only IMU is not given a filter that cannot use its WiFi.
        """
        if not self.buffer:
            return None, Skipped()
        watermark = self.max_t if flush else self.max_t - reorder_ms
        self.buffer.sort(key=lambda item: item[0])
        cut = 0
        while cut < len(self.buffer) and self.buffer[cut][0] <= watermark:
            cut += 1
        if cut == 0:
            return None, Skipped()
        ready = self.buffer[:cut]
        grouped: dict[str, list[Sample]] = {}
        for _, kind, sample in ready:
            grouped.setdefault(kind, []).append(sample)
        batch, skipped = to_batch(self.site, grouped)
        waited = self.max_t - self.buffer[0][0]
        if self.tracker is None and not (_places(batch) or waited >= CHOOSE_WITHIN_MS):
            return None, Skipped()
        self.buffer = self.buffer[cut:]
        # a late WiFi reading may be released behind samples already used
        self.processed_t = max(self.processed_t, ready[-1][0])
        wifi_t = [t for t, kind, _ in ready if kind == "wifi"]
        if wifi_t:
            self.processed_wifi_t = max(self.processed_wifi_t, max(wifi_t))
        # what is left in the buffer is what is newer than the watermark
        self.seen = {key: t for key, t in self.seen.items() if t > watermark}
        self.kinds |= set(grouped)
        self.unflushed = True
        if self.tracker is None:
            kind = choose_kind(self.site, batch, self.kinds)
            self.tracker = make_tracker(kind, self.engines, self.device_id, None)
        return batch, skipped

    def flush_filter(self) -> list[Estimate]:
        """Return what the filter still holds back: the device went quiet, its recording ended."""
        self.unflushed = False
        return [] if self.tracker is None else self.tracker.flush()

    def filter_flushed(self) -> None:
        """Note that the filter's shared engine flushed this device with others."""
        self.unflushed = False

    # -- estimates out -------------------------------------------------------------------

    def emit(
        self, estimates: list[Estimate], *, now: int
    ) -> tuple[list[Position], list[ZoneEvent]]:
        """Return the position messages and zone events of the estimates not yet emitted.

        Estimates at or before the last emitted time are dropped: a filter
        rebuilt from an older snapshot repeats what was already stored. Live
        and refined positions are counted apart (a refined one is older than
        the live ones emitted with it); zones follow the live ones.
        """
        fresh = [e for e in estimates if not e.smoothed and e.t > self.emitted_t]
        refined = [e for e in estimates if e.smoothed and e.t > self.smoothed_t]
        if fresh:
            self.emitted_t = fresh[-1].t
        if refined:
            self.smoothed_t = refined[-1].t
        both = sorted(fresh + refined, key=lambda e: (e.t, e.smoothed))
        positions = [self._position(e, now) for e in both]
        events = [ev for e in fresh for ev in self._zone_events(e)]
        return positions, events

    def _zone_events(self, estimate: Estimate) -> list[ZoneEvent]:
        """Return the enter/exit events this estimate confirms, each at its crossing time.

        Each event carries the position that confirmed it and the zones the
        device is in once it has happened (``zones``).
        """
        if not self.site.zones and not self.zones.inside:
            return []
        margin = self.zone_exit_tolerance * estimate.accuracy
        inside = frozenset(
            z.name
            for z in self.site.zones
            if z.floor == estimate.floor
            and (
                z.contains(estimate.x, estimate.y)
                or (
                    margin > 0
                    and z.name in self.zones.inside
                    and z.near(estimate.x, estimate.y, margin)
                )
            )
        )
        changes = self.zones.update(int(estimate.t), inside)
        if not changes:
            return []
        # the zones after each change, replayed from before this estimate's changes
        now_in = set(self.zones.inside.symmetric_difference(name for _, name, _ in changes))
        events = []
        for event, name, t in changes:
            (now_in.add if event == "enter" else now_in.discard)(name)
            events.append(
                {
                    "type": "zone",
                    "event": event,
                    "zone": name,
                    "device_id": self.device_id,
                    "site_id": self.site.site_id,
                    "floor_id": self.site.floor_ids[estimate.floor],
                    "t": t,
                    "x": round(estimate.x, 3),
                    "y": round(estimate.y, 3),
                    "accuracy": round(estimate.accuracy, 3),
                    "zones": sorted(now_in),
                }
            )
        return events

    def _position(self, estimate: Estimate, now: int) -> Position:
        """Return the API's position message for an estimate computed at ``now``."""
        floor = self.site.model.floors[estimate.floor] if self.site.model.floors else None
        return {
            "type": "position",
            "device_id": self.device_id,
            "site_id": self.site.site_id,
            "floor_id": floor.floor_id if floor else None,
            "t": int(estimate.t),
            "x": round(estimate.x, 3),
            "y": round(estimate.y, 3),
            "z": round(estimate.z, 3),
            "heading": None if math.isnan(estimate.heading) else round(estimate.heading % 360, 2),
            "accuracy": round(estimate.accuracy, 3),
            "speed": None if math.isnan(estimate.speed) else round(estimate.speed, 3),
            "method": estimate.method,
            "computed_at": now,
            "smoothed": estimate.smoothed,
        } | _odometry(estimate)

    # -- lifecycle -----------------------------------------------------------------------

    def snapshot_due(self, every_ms: int) -> bool:
        """Return whether the device's state is due its periodic snapshot.

        Once per ``every_ms`` of measurement time, when the processed time
        crosses the device's own phase of that period (from its key, the same
        in every worker): devices that started, or resumed after a restart,
        in the same second spread their snapshots over the period instead of
        storing them all in one round every ``every_ms``. A device never
        stored is due at once.
        """
        if self.tracker is None or self.processed_t < 0:
            return False
        if self.snapshot_t < 0 or every_ms <= 0:
            return True
        site_id, device_id = self.key
        phase = zlib.crc32(f"{site_id}/{device_id}".encode()) % every_ms
        # slot(t) = ⌊(t + phase) / period⌋
        return (self.processed_t + phase) // every_ms > (self.snapshot_t + phase) // every_ms

    def snapshot(self) -> dict[str, Any]:
        """Return everything needed to resume the device exactly, as snapshot data.

        That is its filter (kind and state), the reorder buffer, the zones it is
        in, the sample kinds it has sent and what it has processed and emitted.
        """
        state: dict[str, Any] = {
            "processed_t": self.processed_t,
            "processed_wifi_t": self.processed_wifi_t,
            "emitted_t": self.emitted_t,
            "smoothed_t": self.smoothed_t,
            "unflushed": self.unflushed,
            **self.zones.snapshot(),
            "kinds": sorted(self.kinds),
            "buffer": _msgpack.encode(self.buffer),
        }
        if self.tracker is not None:
            state["tracker"] = {"kind": self.tracker.kind, "state": self.tracker.snapshot()}
        return state

    def restore(self, state: dict[str, Any]) -> None:
        """Resume from a :meth:`snapshot` (keys a snapshot lacks read as empty)."""
        self.close()
        tracker = state.get("tracker")
        if tracker is not None:
            self.tracker = make_tracker(
                str(tracker["kind"]), self.engines, self.device_id, tracker["state"]
            )
        self.processed_t = self.snapshot_t = int(state["processed_t"])
        self.processed_wifi_t = int(state.get("processed_wifi_t", -1))
        self.emitted_t = int(state.get("emitted_t", -1))
        self.smoothed_t = int(state.get("smoothed_t", -1))
        self.unflushed = bool(state.get("unflushed", False))
        self.zones.restore(state)
        self.kinds = {str(k) for k in state.get("kinds", ())}
        self.buffer = [(int(t), str(k), s) for t, k, s in _buffered(state.get("buffer", b""))]
        self.seen = {_key(k, s): t for t, k, s in self.buffer}
        self.max_t = max([self.processed_t] + [t for t, _, _ in self.buffer])

    def use_site(self, engines: SiteEngines) -> None:
        """Move the device onto another version of its site, its filter rebuilt from its state."""
        if self.tracker is not None:
            kind = self.tracker.kind
            state: dict[str, Any] | None = self.tracker.snapshot()
            self.close()
            wanted = radio_kind(engines.site)
            if kind in RADIO_KINDS and self.kinds & {"wifi", "ble"} and wanted != kind:
                # a build or an engine change gave the site a better filter for this device
                kind, state = wanted, None
            self.tracker = make_tracker(kind, engines, self.device_id, state)
        self.engines = engines

    def close(self) -> None:
        """Free the device's filter (its slot in a shared engine)."""
        if self.tracker is not None:
            self.tracker.close()
        self.tracker = None
