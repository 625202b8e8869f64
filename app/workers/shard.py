"""A shard's devices: route messages to device sessions, run their filters, store positions.

This is the worker's unit of work and knows nothing of processes or queues,
so the same class runs in a worker process, in a thread, or in a test.
Devices whose filters live in a site's batched engine (the particle filter)
are updated together: one engine call per site per round of messages.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Sequence
from typing import TypeVar

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from app.analytics.service import store_zone_events
from app.core.config import Settings
from app.core.db import session_scope
from app.core.identity import DeviceKey
from app.core.outages import retry_through_outage
from app.devices.service import touch_devices
from app.engine.samples import Batch, Estimate
from app.outputs.outbox import Outbox
from app.positions.models import PositionRecord
from app.positions.service import store as store_positions
from app.workers import snapshots
from app.workers.device import DeviceSession, public
from app.workers.messages import Done, Emitted, Ingest, Position, Stats, ZoneEvent
from app.workers.sites import SiteCache
from app.workers.snapshot_store import DatabaseSnapshots, SnapshotStore
from app.workers.trackers import BatchEngine, DeviceTracker, SiteEngines

Clock = Callable[[], int]
"""The wall clock in epoch milliseconds."""
Snapshot = tuple[DeviceSession, int, int, bytes]
"""A device, the measurement time of its snapshot, the batches it holds, and the snapshot."""
T = TypeVar("T")


class Shard:
    """Owns the devices of one shard and processes their batches in arrival order.

    Its owner passes the wall clock (``clock``, epoch milliseconds), so the
    silence that flushes and evicts devices can be driven by a test.
    """

    def __init__(
        self,
        *,
        shard: int,
        settings: Settings,
        sessions: sessionmaker[Session],
        clock: Clock,
        snapshots: SnapshotStore | None = None,
        sites: SiteCache | None = None,
        on_storage_wait: Callable[[], None] = lambda: None,
    ) -> None:
        self.shard = shard
        self.settings = settings
        self.sessions = sessions
        self.clock = clock
        self.store = snapshots or DatabaseSnapshots()
        self.sites = sites or SiteCache(settings=settings, sessions=sessions)
        self.on_storage_wait = on_storage_wait
        self.outbox = Outbox(refresh_ms=round(settings.output_refresh_s * 1000), clock=clock)
        self.devices: dict[DeviceKey, DeviceSession] = {}
        """The devices held here, least recently heard first (``_heard``)."""
        self.counters: Counter[str] = Counter()
        self.update_seconds = 0.0
        self._scanned_at = 0
        self._covered: list[DeviceSession] = []

    # -- sites and devices -------------------------------------------------------------

    def _device(self, db: Session, device_id: str, engines: SiteEngines, now: int) -> DeviceSession:
        """Return the session of ``device_id`` in the engines' site, resumed from its snapshot
        when it has none here; a device of the same id in another site is another session."""
        site_id = engines.site.site_id
        device = self.devices.get((site_id, device_id))
        if device is not None:
            if device.engines is not engines:
                # the map changed: rebuild the filter on the new site from its own state
                device.use_site(engines)
            return device
        device = DeviceSession(
            device_id=device_id,
            engines=engines,
            now=now,
            zone_dwell_ms=round(self.settings.zone_dwell_s * 1000),
            zone_exit_tolerance=self.settings.zone_exit_tolerance,
        )
        stored = self.store.load(db, device.key)
        if stored is not None:
            device.restore(snapshots.decode(stored))
            # Re-delivered batches rebuild the filter from an older snapshot; what was
            # already stored must not be emitted twice.
            last = dict(
                db.execute(
                    select(PositionRecord.smoothed, func.max(PositionRecord.t))
                    .where(PositionRecord.site_id == site_id, PositionRecord.device_id == device_id)
                    .group_by(PositionRecord.smoothed)
                ).all()
            )
            device.emitted_t = max(device.emitted_t, int(last.get(False, -1)))
            device.smoothed_t = max(device.smoothed_t, int(last.get(True, -1)))
            self.counters["restored"] += 1
        self.devices[device.key] = device
        return device

    def _heard(self, device: DeviceSession) -> None:
        """Move a device that has just been heard to the end of ``devices``: kept in the
        order of ``last_seen``, the silence scan stops at the first recent device (after
        the wall clock steps back, a flush waits for at most the step)."""
        self.devices[device.key] = self.devices.pop(device.key)

    def _evict(self, device: DeviceSession) -> None:
        device.close()
        self.devices.pop(device.key, None)

    # -- processing ----------------------------------------------------------------------

    def _storage(self, work: Callable[[Session], T], what: str) -> T:
        """Run ``work`` in a transaction of its own, again and again through a storage outage.

        The shard stalls while the database (or Redis) is away: its batches stay
        unacknowledged in the broker, and what it computed is stored, not dropped,
        once the store returns.
        """

        def attempt() -> T:
            with session_scope(self.sessions) as db:
                return work(db)

        return retry_through_outage(
            attempt, what=f"shard {self.shard}: {what}", on_wait=self.on_storage_wait
        )

    def _route(self, db: Session, messages: list[Ingest], now: int) -> list[DeviceSession | None]:
        """Return each message's device session (None for an unknown site), loading its site
        and its snapshot as needed; repeatable, as it changes nothing a retry would redo."""
        routed: list[DeviceSession | None] = []
        for msg in messages:
            engines = self.sites.get(db, msg.site_id, msg.version)
            routed.append(
                None if engines is None else self._device(db, msg.device_id, engines, now)
            )
        return routed

    def handle(self, messages: list[Ingest]) -> list[Done]:
        """Process ingest messages; positions are stored before any result is returned.

        What the database must give (sites, snapshots of devices new here) is read
        first, and what the round produced is written last, each retried through
        an outage, so a device's samples are used once whatever the database does.
        """
        started = time.perf_counter()
        results: list[Done] = []
        rows: list[Position] = []
        events: list[ZoneEvent] = []
        # a device's silence is timed from when its samples were taken in
        now = self.clock()
        routed = self._storage(lambda db: self._route(db, messages, now), "reading devices")
        work: list[tuple[DeviceSession | None, Batch | None]] = []
        counts: list[tuple[int, int, int]] = []
        for msg, device in zip(messages, routed, strict=True):
            if device is None:
                self.counters["dropped_unknown_site"] += 1
                work.append((None, None))
                counts.append((0, 0, 0))
                continue
            accepted, late, duplicate = device.add(msg.samples, now=now)
            self._heard(device)
            device.consumed += 1
            self.counters["samples"] += accepted
            self.counters["late"] += late
            self.counters["duplicate"] += duplicate
            work.append((device, self._take(device, flush=msg.flush)))
            counts.append((accepted, late, duplicate))
        outputs = self._run(work)
        now = self.clock()
        for msg, (device, _), (accepted, late, duplicate), estimates in zip(
            messages, work, counts, outputs, strict=True
        ):
            if device is None:
                results.append(Done(msg.batch_id, msg.site_id, msg.device_id))
                continue
            positions, emitted = self._emit(device, estimates, now)
            rows.extend(positions)
            events.extend(emitted)
            results.append(
                Done(
                    msg.batch_id,
                    msg.site_id,
                    msg.device_id,
                    accepted=accepted,
                    late=late,
                    duplicate=duplicate,
                    positions=[public(p) for p in positions],
                    events=emitted,
                    processed_t=device.processed_t,
                    processed_wifi_t=device.processed_wifi_t,
                )
            )
        touched = list({d.key: d for d, _ in work if d is not None}.values())
        heard = [(d.key, d.max_t) for d in touched]
        snaps = self._due_snapshots(touched, force=False)

        def write(db: Session) -> None:
            store_positions(db, [_row(p) for p in rows])
            store_zone_events(db, events)
            # in the same transaction: a position is stored with its outbox rows or not at all
            self.counters["outbox"] += self.outbox.add(db, [*rows, *events])
            touch_devices(db=db, heard=heard, now=now)
            self._write_snapshots(db, snaps)

        self._storage(write, "storing positions")
        self._saved(snaps)
        # a device is not silent while its batch is being positioned and stored: a slow
        # round (a site's first use, a storage outage) must not flush what the next batch
        # would have placed
        done_at = self.clock()
        for device in touched:
            device.last_seen = max(device.last_seen, done_at)
        self.update_seconds += time.perf_counter() - started
        self.counters["positions"] += len(rows)
        return results

    def _take(self, device: DeviceSession, *, flush: bool) -> Batch | None:
        batch, skipped = device.take(reorder_ms=self.settings.reorder_window_ms, flush=flush)
        self.counters["unknown_ids"] += skipped.unknown_ids
        self.counters["stale"] += skipped.stale
        return batch

    def _run(
        self, work: Sequence[tuple[DeviceSession | None, Batch | None]]
    ) -> list[list[Estimate]]:
        """Run every batch through its device's filter, devices of a shared engine together.

        Round k holds each device's k-th batch of this group, so a device's
        batches are still processed in order; each shared engine is called once
        per round.
        """
        outputs: list[list[Estimate]] = [[] for _ in work]
        seen: Counter[DeviceKey] = Counter()
        rounds: dict[int, list[tuple[int, DeviceTracker, str, Batch]]] = {}
        for i, (device, batch) in enumerate(work):
            if device is None or batch is None or device.tracker is None:
                continue
            # a shared engine is one site's: within it the device id is the device
            rounds.setdefault(seen[device.key], []).append(
                (i, device.tracker, device.device_id, batch)
            )
            seen[device.key] += 1
        for k in sorted(rounds):
            together: dict[int, tuple[BatchEngine, list[tuple[int, str, Batch]]]] = {}
            for i, tracker, device_id, batch in rounds[k]:
                engine = tracker.shared_engine
                if engine is None:
                    outputs[i] = tracker.process(batch)
                else:
                    together.setdefault(id(engine), (engine, []))[1].append((i, device_id, batch))
            for engine, items in together.values():
                estimates = engine.process({device_id: batch for _, device_id, batch in items})
                for i, device_id, _ in items:
                    outputs[i] = estimates[device_id]
        return outputs

    def _emit(
        self, device: DeviceSession, estimates: list[Estimate], now: int
    ) -> tuple[list[Position], list[ZoneEvent]]:
        positions, events = device.emit(estimates, now=now)
        self.counters["suppressed_repeats"] += len(estimates) - len(positions)
        return positions, events

    def _flush(
        self, devices: list[DeviceSession], now: int
    ) -> tuple[list[Emitted], list[Position]]:
        """Position everything the quiet ``devices`` buffer or their filters hold back.

        Returns the results to report and the position rows to store.
        """
        results: list[Emitted] = []
        rows: list[Position] = []
        work = [(d, self._take(d, flush=True)) for d in devices]
        ran = self._run(work)
        # silence ends a recording: position its last, incomplete window too
        held = self._flush_filters(devices)
        for device, estimates, last in zip(devices, ran, held, strict=True):
            estimates = estimates + last
            positions, events = self._emit(device, estimates, now)
            rows.extend(positions)
            if positions or events:
                results.append(
                    Emitted(
                        device.site.site_id,
                        device.device_id,
                        [public(p) for p in positions],
                        events,
                    )
                )
        self.counters["positions"] += len(rows)
        return results, rows

    def _flush_filters(self, devices: list[DeviceSession]) -> list[list[Estimate]]:
        """Return what each device's filter still holds back, the devices of a shared engine
        flushed in one engine call (one call per device became much of a worker's time once
        thousands of devices waited longer than ``flush_after_s`` between their batches)."""
        held: list[list[Estimate]] = [[] for _ in devices]
        together: dict[int, tuple[BatchEngine, list[int]]] = {}
        for i, device in enumerate(devices):
            engine = None if device.tracker is None else device.tracker.shared_engine
            if engine is None:
                held[i] = device.flush_filter()
            else:
                together.setdefault(id(engine), (engine, []))[1].append(i)
        for engine, rows in together.values():
            estimates = engine.flush([devices[i].device_id for i in rows])
            for i in rows:
                devices[i].filter_flushed()
                held[i] = estimates[devices[i].device_id]
        return held

    def _store_flushed(
        self, results: list[Emitted], rows: list[Position], snaps: list[Snapshot], what: str
    ) -> None:
        """Store flushed positions, their zone events with their outbox rows, and snapshots,
        through an outage."""
        events = [event for result in results for event in result.events]

        def write(db: Session) -> None:
            store_positions(db, [_row(p) for p in rows])
            store_zone_events(db, events)
            self.counters["outbox"] += self.outbox.add(db, [*rows, *events])
            self._write_snapshots(db, snaps)

        if rows or events or snaps:
            self._storage(write, what)
            self._saved(snaps)

    def tick(self) -> list[Emitted]:
        """Flush quiet devices' buffers and filters and snapshot them; evict idle devices
        (with a snapshot).

        A device is quiet after ``flush_after_s`` of silence, or ``flush_after_periods``
        of its own upload period when that is longer.

        Does nothing within ``silence_scan_every_ms`` of the last scan, unless buffers are
        to be flushed at once (``flush_after_s`` 0).
        """
        now = self.clock()
        # the scan visits every device, and the worker loop calls tick after each round
        recently = now - self._scanned_at < self.settings.silence_scan_every_ms
        if self.settings.flush_after_s > 0 and recently:
            return []
        self._scanned_at = now
        flush_ms = self.settings.flush_after_s * 1000
        evict_ms = self.settings.idle_evict_s * 1000
        periods = self.settings.flush_after_periods
        # no device is quiet or idle before the shorter of the two silences
        horizon = min(flush_ms, evict_ms)
        quiet: list[DeviceSession] = []
        idle: list[DeviceSession] = []
        for d in self.devices.values():
            silent = now - d.last_seen
            if silent < horizon:
                break  # and so is every device after it
            if d.pending:
                if silent >= d.quiet_after_ms(flush_ms, periods):
                    quiet.append(d)
            elif silent >= evict_ms:
                idle.append(d)
        if not quiet and not idle:
            return []
        results, rows = self._flush(quiet, now)
        # a device gone quiet is snapshotted once: the batches it holds are then covered
        snaps = self._due_snapshots(quiet + idle, force=True)
        self._store_flushed(results, rows, snaps, "storing flushed positions")
        for device in idle:
            # its snapshot is stored, or it never held a state worth one
            device.covered = device.consumed
            self._covered.append(device)
            self._evict(device)
            self.counters["evicted"] += 1
        return results

    def drain(self) -> list[Emitted]:
        """Position everything buffered, snapshot every device and let them all go.

        At stop and when the shard is handed to another worker: whoever runs the
        shard next resumes each device from its snapshot, with nothing left behind.
        """
        now = self.clock()
        devices = list(self.devices.values())
        results, rows = self._flush([d for d in devices if d.pending], now)
        snaps = self._due_snapshots(devices, force=True)
        self._store_flushed(results, rows, snaps, "draining")
        for device in devices:
            self._evict(device)
            self.counters["evicted"] += 1
        return results

    def close(self) -> None:
        """Let every device go without storing anything: the shard is no longer this worker's."""
        for device in list(self.devices.values()):
            self._evict(device)

    def _due_snapshots(self, devices: list[DeviceSession], *, force: bool) -> list[Snapshot]:
        """Return the snapshots of ``devices`` that are due (all of them with ``force``)."""
        snaps = []
        every_ms = self.settings.snapshot_every_ms
        for device in devices:
            stored = device.tracker is not None and device.processed_t >= 0
            if not stored or not (force or device.snapshot_due(every_ms)):
                continue
            blob = snapshots.encode(device.snapshot())
            snaps.append((device, device.processed_t, device.consumed, blob))
        return snaps

    def _write_snapshots(self, db: Session, snaps: list[Snapshot]) -> None:
        self.store.save_all(db, [(device.key, t, blob) for device, t, _, blob in snaps])

    def _saved(self, snaps: list[Snapshot]) -> None:
        """Note the snapshots as stored, once their transaction committed."""
        for device, t, consumed, _ in snaps:
            device.snapshot_t = t
            device.covered = consumed
            self._covered.append(device)
        self.counters["snapshots"] += len(snaps)

    def has_newly_covered(self) -> bool:
        """Return whether snapshots were stored since the last :meth:`newly_covered`."""
        return bool(self._covered)

    def newly_covered(self) -> list[DeviceSession]:
        """Return (and forget) the devices whose snapshots were stored since the last call."""
        covered, self._covered = self._covered, []
        return covered

    def stats(self) -> Stats:
        """Return counters for the API's metrics."""
        return Stats(self.shard, len(self.devices), dict(self.counters), self.update_seconds)


def _row(position: Position) -> Position:
    return {k: v for k, v in position.items() if k != "type"}
