"""The API side of the workers: submit batches, await results, fan positions out."""

from __future__ import annotations

import asyncio
import itertools
import logging
import time
import uuid
from collections import Counter
from dataclasses import dataclass

from app.core.config import Settings
from app.core.errors import DomainError, Overloaded, ProcessingFailed, Unavailable
from app.core.identity import DeviceKey
from app.core.metrics import Metrics
from app.core.outages import RETRY_AFTER_S
from app.positions.hub import PositionHub
from app.workers.broker import Broker, MemoryBroker
from app.workers.messages import (
    Done,
    Emitted,
    Ingest,
    Position,
    Result,
    Sample,
    Stats,
    ZoneEvent,
)
from app.workers.redis_broker import LocalRedisWorkers, RedisBroker
from app.workers.shards import shard_of

log = logging.getLogger(__name__)


@dataclass
class Outcome:
    """What the workers did with one batch; ``error`` says why it was not processed."""

    accepted: int
    late: int
    positions: list[Position]
    error: DomainError | None = None


class Runtime:
    """Owns the broker; routes batches by device, resolves waits, feeds the hub.

    Everything it keeps per device is keyed by (site, device).
    """

    def __init__(self, settings: Settings, metrics: Metrics, broker: Broker | None = None) -> None:
        self.settings = settings
        self.metrics = metrics
        self.local_workers: LocalRedisWorkers | None = None
        if broker is not None:
            self.broker = broker
        elif settings.broker == "memory":
            self.broker = MemoryBroker(settings, settings.worker_count)
        else:
            self.broker = RedisBroker(settings)
            if settings.worker_count > 0:
                self.local_workers = LocalRedisWorkers(settings, settings.worker_count)
        self.hub = PositionHub(metrics, settings.ws_queue_size)
        self.loop: asyncio.AbstractEventLoop | None = None
        self.waiting: dict[str, asyncio.Future[Outcome]] = {}
        self.sent_at: dict[str, float] = {}
        self.inflight: Counter[DeviceKey] = Counter()
        self.processed_t: dict[DeviceKey, int] = {}
        self.processed_wifi_t: dict[DeviceKey, int] = {}
        self.worker_counters: dict[int, dict[str, int]] = {}
        self.parked: dict[DeviceKey, tuple[int, Ingest]] = {}
        self._ids = itertools.count()
        self._prefix = uuid.uuid4().hex[:12]
        self._forwarder: asyncio.Task[None] | None = None

    async def start(self) -> None:
        """Start the broker's consumers (blocking start-up runs in a thread)."""
        self.loop = asyncio.get_running_loop()
        if isinstance(self.broker, MemoryBroker):
            self.broker.on_restart = lambda shard: self.metrics.worker_restarts.labels(
                str(shard)
            ).inc()
        await self.broker.start(self._dispatch)
        self._forwarder = asyncio.create_task(self._forward_parked())
        if self.local_workers is not None:
            self.local_workers.start()

    async def stop(self) -> None:
        """Stop the broker; its workers snapshot their devices first."""
        if self._forwarder is not None:
            self._forwarder.cancel()
        if self.local_workers is not None:
            await asyncio.to_thread(self.local_workers.stop)
        await self.broker.stop()

    # -- submit ------------------------------------------------------------------------

    def submit(
        self,
        *,
        site_id: str,
        device_id: str,
        version: int,
        samples: dict[str, list[Sample]],
        wait: bool,
        flush: bool | None = None,
    ) -> tuple[str, asyncio.Future[Outcome] | None]:
        """Queue a device's samples on its shard; with ``wait`` return a future of the outcome.

        ``flush`` (default: ``wait``) has the worker process the device's whole
        reorder buffer at once instead of holding its newest samples back.

        Raises Overloaded when the device or its shard is over its bound, Unavailable
        while the broker cannot take batches.
        """
        if not self.broker.available():
            raise Unavailable("Redis is unavailable; retry later", retry_after_s=RETRY_AFTER_S)
        key = (site_id, device_id)
        shard = shard_of(key, self.broker.shards)
        if self.inflight[key] >= self.settings.max_inflight_batches:
            self.metrics.ingest_rejected.labels("device_backlog").inc()
            raise Overloaded(
                f"device '{device_id}' has too many unprocessed batches", retry_after_s=1
            )
        overloaded = self.broker.backlog(shard) >= self.settings.shard_backlog
        if overloaded and self.settings.overload_policy == "reject":
            self.metrics.ingest_rejected.labels("shard_backlog").inc()
            raise Overloaded("the device's worker is overloaded", retry_after_s=1)
        batch_id = f"{self._prefix}-{next(self._ids)}"
        future: asyncio.Future[Outcome] | None = None
        if wait:
            assert self.loop is not None
            future = self.loop.create_future()
            self.waiting[batch_id] = future
        self.inflight[key] += 1
        self.sent_at[batch_id] = time.perf_counter()
        message = Ingest(
            batch_id, site_id, device_id, version, samples, wait if flush is None else flush
        )
        if overloaded:
            # policy "latest": park the batch; a newer one from the device replaces it
            superseded = self.parked.pop(key, None)
            if superseded is not None:
                self._supersede(superseded[1])
            self.parked[key] = (shard, message)
        else:
            self.broker.publish(shard, message)
        self.metrics.queue_depth.labels(str(shard)).set(self.broker.backlog(shard))
        return batch_id, future

    def _supersede(self, message: Ingest) -> None:
        batch_id, key = message.batch_id, (message.site_id, message.device_id)
        dropped = sum(len(items) for items in message.samples.values())
        self.metrics.dropped_samples.labels("superseded").inc(dropped)
        self.sent_at.pop(batch_id, None)
        self._settle(key)
        future = self.waiting.pop(batch_id, None)
        if future is not None and not future.done():
            reason = Overloaded(
                "dropped for a newer batch of the device (overload)", retry_after_s=1
            )
            future.set_result(Outcome(0, 0, [], reason))

    async def _forward_parked(self) -> None:
        """Publish parked batches as their shards' backlogs fall below the bound."""
        while True:
            await asyncio.sleep(0.1)
            for key, (shard, message) in list(self.parked.items()):
                if self.broker.backlog(shard) < self.settings.shard_backlog:
                    del self.parked[key]
                    self.broker.publish(shard, message)

    def last_processed_t(self, key: DeviceKey) -> int:
        """Return the newest measurement time the worker of the device (site, device) has
        processed (-1: none). Samples at or before it arrive too late to be used."""
        return self.processed_t.get(key, -1)

    def _settle(self, key: DeviceKey) -> None:
        """Count one of the device's batches as no longer in flight."""
        self.inflight[key] -= 1
        if self.inflight[key] <= 0:
            del self.inflight[key]

    def last_processed_wifi_t(self, key: DeviceKey) -> int:
        """Return the newest WiFi reading time the worker of the device has used (-1: none)."""
        return self.processed_wifi_t.get(key, -1)

    # -- results ----------------------------------------------------------------------

    def _dispatch(self, results: list[Result]) -> None:
        fan_out: list[Position | ZoneEvent] = []
        for result in results:
            if isinstance(result, Stats):
                self._stats(result)
            if not isinstance(result, Done | Emitted):
                continue
            if isinstance(result, Done):
                self._done(result)
            fan_out.extend(result.positions)
            fan_out.extend(result.events)
            self.metrics.positions.inc(len(result.positions))
            self.metrics.zone_events.inc(len(result.events))
        if fan_out:
            self.hub.publish(fan_out)

    def _done(self, result: Done) -> None:
        batch_id = result.batch_id
        key = (result.site_id, result.device_id)
        if batch_id in self.sent_at:
            self.metrics.ingest_to_position.observe(
                time.perf_counter() - self.sent_at.pop(batch_id)
            )
            self._settle(key)
        if result.processed_t is not None:
            self.processed_t[key] = max(self.processed_t.get(key, -1), result.processed_t)
            wifi_t = -1 if result.processed_wifi_t is None else result.processed_wifi_t
            self.processed_wifi_t[key] = max(self.processed_wifi_t.get(key, -1), wifi_t)
        future = self.waiting.pop(batch_id, None)
        if future is not None and not future.done():
            error = result.error
            future.set_result(
                Outcome(
                    result.accepted,
                    result.late,
                    result.positions,
                    None if error is None else ProcessingFailed(f"processing failed: {error}"),
                )
            )

    def _stats(self, result: Stats) -> None:
        shard = result.shard
        previous = self.worker_counters.get(shard, {})
        counters = result.counters
        # workers report running totals; a restarted worker starts again from zero
        for outcome, key in (
            ("used", "samples"),
            ("late", "late"),
            ("duplicate", "duplicate"),
            ("unknown_id", "unknown_ids"),
            ("stale", "stale"),
        ):
            delta = counters.get(key, 0) - previous.get(key, 0)
            self.metrics.worker_samples.labels(outcome).inc(
                delta if delta >= 0 else counters.get(key, 0)
            )
        self.worker_counters[shard] = counters
        self.metrics.worker_devices.labels(str(shard)).set(result.devices)
        self.metrics.worker_update_seconds.labels(str(shard)).set(result.update_seconds)
        self.metrics.queue_depth.labels(str(shard)).set(self.broker.backlog(shard))
