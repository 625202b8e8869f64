"""A shard's devices: route messages to device sessions, run their filters, store positions.

This is the worker's unit of work and knows nothing of processes or queues,
so the same class runs in a worker process, in a thread, or in a test.
Devices whose filters live in a site's batched engine (the particle filter)
are updated together: one engine call per site per round of messages.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from typing import Any

from sqlalchemy import func, insert, select
from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.db import session_scope
from app.core.time import now_ms
from app.engine.samples import Batch, Estimate
from app.positions.models import PositionRecord
from app.sites.assembly import assemble_site
from app.sites.models import Site
from app.workers import snapshots
from app.workers.device import DeviceSession
from app.workers.snapshot_store import DatabaseSnapshots, SnapshotStore
from app.workers.trackers import (
    RADIO_KINDS,
    EngineDevice,
    SiteEngines,
    choose_kind,
    kind_of,
    make_tracker,
    radio_kind,
)

log = logging.getLogger(__name__)

Message = dict[str, Any]

SCAN_EVERY_MS = 100
"""Quiet and idle devices are looked for at most this often: the scan visits every
device, and the worker loop calls ``tick`` after each group of messages."""


class Shard:
    """Owns the devices of one shard and processes their batches in arrival order."""

    def __init__(
        self,
        *,
        shard: int,
        settings: Settings,
        sessions: sessionmaker[Session],
        snapshots: SnapshotStore | None = None,
        engines: dict[str, SiteEngines] | None = None,
    ) -> None:
        self.shard = shard
        self.settings = settings
        self.sessions = sessions
        self.store = snapshots or DatabaseSnapshots()
        # shards of one process share their sites' engines: a mall's rasters are tens of MB
        self.engines: dict[str, SiteEngines] = {} if engines is None else engines
        self.devices: dict[str, DeviceSession] = {}
        self.counters: Counter[str] = Counter()
        self.update_seconds = 0.0
        self._scanned_at = 0

    # -- sites and devices -------------------------------------------------------------

    def _site(self, db: Session, site_id: str, version: int) -> SiteEngines | None:
        cached = self.engines.get(site_id)
        if cached is not None and cached.site.version >= version:
            return cached
        row = db.get(Site, site_id)
        if row is None:
            self.engines.pop(site_id, None)
            return None
        loaded = assemble_site(db=db, site=row, raster_cell=self.settings.raster_cell)
        engines = SiteEngines.for_site(loaded)
        self.engines[site_id] = engines
        log.info("shard %d loaded site %s v%d", self.shard, site_id, loaded.version)
        return engines

    def _device(self, db: Session, device_id: str, engines: SiteEngines) -> DeviceSession:
        site = engines.site
        device = self.devices.get(device_id)
        if device is not None and device.site.site_id == site.site_id:
            if device.site is not site:
                # the map changed: rebuild the filter on the new site from its own state
                self._rebuild(device, engines)
            return device
        if device is not None:
            self._close(device)
        stored = self.store.load(db, device_id)
        state = snapshots.decode(stored[1]) if stored and stored[0] == site.site_id else None
        device = DeviceSession(device_id=device_id, site=site)
        if state is not None:
            tracker = state["tracker"]
            device.tracker = make_tracker(tracker["kind"], engines, device_id, tracker["state"])
            device.processed_t = device.max_t = device.snapshot_t = int(state["processed_t"])
            device.zones = frozenset(str(z) for z in state.get("zones", ()))
            # Re-delivered batches rebuild the filter from an older snapshot; what was
            # already stored must not be emitted twice.
            last = db.scalar(
                select(func.max(PositionRecord.t)).where(PositionRecord.device_id == device_id)
            )
            device.emitted_t = -1 if last is None else int(last)
            self.counters["restored"] += 1
        self.devices[device_id] = device
        return device

    def _rebuild(self, device: DeviceSession, engines: SiteEngines) -> None:
        if device.tracker is not None:
            kind, state = kind_of(device.tracker), device.tracker.snapshot()
            self._close_tracker(device)
            wanted = radio_kind(engines.site)
            if kind in RADIO_KINDS and device.kinds & {"wifi", "ble"} and wanted != kind:
                # a build or an engine change gave the site a better filter for this device
                kind, state = wanted, None
            device.tracker = make_tracker(kind, engines, device.device_id, state)
        device.site = engines.site

    def _close_tracker(self, device: DeviceSession) -> None:
        if isinstance(device.tracker, EngineDevice):
            device.tracker.close()
        device.tracker = None

    def _close(self, device: DeviceSession) -> None:
        self._close_tracker(device)
        self.devices.pop(device.device_id, None)

    # -- processing ----------------------------------------------------------------------

    def handle(self, messages: list[Message]) -> list[Message]:
        """Process ingest messages; positions are stored before any result is returned."""
        started = time.perf_counter()
        results: list[Message] = []
        rows: list[Message] = []
        with session_scope(self.sessions) as db:
            work: list[tuple[DeviceSession | None, Batch | None]] = []
            for msg in messages:
                done: Message = {
                    "type": "done",
                    "batch_id": msg["batch_id"],
                    "device_id": msg["device_id"],
                }
                engines = self._site(db, msg["site_id"], msg["version"])
                if engines is None:
                    self.counters["dropped_unknown_site"] += 1
                    results.append(
                        done
                        | {"accepted": 0, "late": 0, "duplicate": 0, "positions": [], "events": []}
                    )
                    work.append((None, None))
                    continue
                device = self._device(db, msg["device_id"], engines)
                accepted, late, duplicate = device.add(msg["samples"])
                self.counters["samples"] += accepted
                self.counters["late"] += late
                self.counters["duplicate"] += duplicate
                batch = self._take(device, flush=bool(msg.get("flush")))
                results.append(done | {"accepted": accepted, "late": late, "duplicate": duplicate})
                work.append((device, batch))
            outputs = self._run(work)
            for result, (device, _), estimates in zip(results, work, outputs, strict=True):
                if device is None:
                    continue
                positions, events = self._emit(device, estimates)
                rows.extend(positions)
                result.update(positions=positions, events=events, processed_t=device.processed_t)
            if rows:
                db.execute(insert(PositionRecord), [_row(p) for p in rows])
            touched = {d.device_id for d, _ in work if d is not None}
            self._snapshot_due(db, touched, force=False)
        self.update_seconds += time.perf_counter() - started
        self.counters["positions"] += len(rows)
        return results

    def _take(self, device: DeviceSession, *, flush: bool) -> Batch | None:
        unknown_before = device.unknown
        batch = device.take(reorder_ms=self.settings.reorder_window_ms, flush=flush)
        self.counters["unknown_ids"] += device.unknown - unknown_before
        if batch is not None:
            device.unflushed = True
        if batch is not None and device.tracker is None:
            engines = self.engines[device.site.site_id]
            device.tracker = make_tracker(
                choose_kind(device.site, batch, device.kinds), engines, device.device_id, None
            )
        return batch

    def _run(self, work: list[tuple[DeviceSession | None, Batch | None]]) -> list[list[Estimate]]:
        """Run every batch through its device's filter, engine devices batched per round.

        Round k holds each device's k-th batch of this group, so a device's
        batches are still processed in order.
        """
        outputs: list[list[Estimate]] = [[] for _ in work]
        seen: Counter[str] = Counter()
        rounds: dict[int, list[int]] = {}
        for i, (device, batch) in enumerate(work):
            if device is None or batch is None or device.tracker is None:
                continue
            rounds.setdefault(seen[device.device_id], []).append(i)
            seen[device.device_id] += 1
        for k in sorted(rounds):
            by_engine: dict[int, list[int]] = {}
            for i in rounds[k]:
                device, batch = work[i]
                assert device is not None and batch is not None
                if isinstance(device.tracker, EngineDevice):
                    by_engine.setdefault(id(device.tracker.engine), []).append(i)
                else:
                    outputs[i] = device.tracker.process(batch)  # type: ignore[union-attr]
            for items in by_engine.values():
                engine = work[items[0]][0].tracker.engine  # type: ignore[union-attr]
                batches = {work[i][0].device_id: work[i][1] for i in items}  # type: ignore[union-attr]
                estimates = engine.process(batches)
                for i in items:
                    outputs[i] = estimates[work[i][0].device_id]  # type: ignore[union-attr]
        return outputs

    def _emit(
        self, device: DeviceSession, estimates: list[Estimate]
    ) -> tuple[list[Message], list[Message]]:
        fresh = [e for e in estimates if e.t > device.emitted_t]
        self.counters["suppressed_repeats"] += len(estimates) - len(fresh)
        if fresh:
            device.emitted_t = fresh[-1].t
        positions = [device.position(e) for e in fresh]
        events = [ev for e in fresh for ev in device.zone_events(e)]
        return positions, events

    def tick(self) -> list[Message]:
        """Flush quiet devices' buffers and filters; evict idle devices (with a snapshot).

        Does nothing within ``SCAN_EVERY_MS`` of the last scan, unless buffers are
        to be flushed at once (``flush_after_s`` 0, as on shutdown).
        """
        now = now_ms()
        if self.settings.flush_after_s > 0 and now - self._scanned_at < SCAN_EVERY_MS:
            return []
        self._scanned_at = now
        flush_ms = self.settings.flush_after_s * 1000
        evict_ms = self.settings.idle_evict_s * 1000
        pending = {d.device_id for d in self.devices.values() if d.buffer or d.unflushed}
        quiet = [
            d
            for d in self.devices.values()
            if d.device_id in pending and now - d.last_seen_wall >= flush_ms
        ]
        idle = [
            d
            for d in self.devices.values()
            if d.device_id not in pending and now - d.last_seen_wall >= evict_ms
        ]
        if not quiet and not idle:
            return []
        results: list[Message] = []
        rows: list[Message] = []
        with session_scope(self.sessions) as db:
            work = [(d, self._take(d, flush=True)) for d in quiet]
            for (device, _), estimates in zip(work, self._run(work), strict=True):
                if isinstance(device.tracker, EngineDevice):
                    # silence ends a recording: position its last, incomplete window too
                    estimates = estimates + device.tracker.flush()
                device.unflushed = False
                positions, events = self._emit(device, estimates)
                rows.extend(positions)
                if positions or events:
                    results.append(
                        {
                            "type": "emitted",
                            "device_id": device.device_id,
                            "positions": positions,
                            "events": events,
                        }
                    )
            if rows:
                db.execute(insert(PositionRecord), [_row(p) for p in rows])
            self._snapshot_due(db, {d.device_id for d in quiet}, force=False)
            self._snapshot_due(db, {d.device_id for d in idle}, force=True)
        for device in idle:
            self._close(device)
            self.counters["evicted"] += 1
        self.counters["positions"] += len(rows)
        return results

    def _snapshot_due(self, db: Session, device_ids: set[str], *, force: bool) -> None:
        for device_id in device_ids:
            device = self.devices[device_id]
            due = device.processed_t - device.snapshot_t >= self.settings.snapshot_every_ms
            if device.tracker is None or device.processed_t < 0 or not (force or due):
                continue
            tracker = {"kind": kind_of(device.tracker), "state": device.tracker.snapshot()}
            state = {
                "tracker": tracker,
                "processed_t": device.processed_t,
                "zones": sorted(device.zones),
            }
            self.store.save(
                db, device_id, device.site.site_id, device.processed_t, snapshots.encode(state)
            )
            device.snapshot_t = device.processed_t
            self.counters["snapshots"] += 1

    def stats(self) -> Message:
        """Return counters for the API's metrics."""
        return {
            "type": "stats",
            "shard": self.shard,
            "devices": len(self.devices),
            "counters": dict(self.counters),
            "update_seconds": self.update_seconds,
        }


def _row(position: Message) -> Message:
    return {k: v for k, v in position.items() if k != "type"}
