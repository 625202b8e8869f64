"""Redis Streams between stateless API nodes and filter-worker nodes.

- One stream per shard (``locus:shard:<n>``); API nodes ``XADD`` batches
  (``MAXLEN ~`` bounded) and workers read them with the consumer group
  ``workers``, acknowledging (``XACK``) an entry only once a stored snapshot
  of its device holds it (``app.workers.coverage``). Processed entries that
  wait for it are counted in ``locus:held:<n>``, so the backlog is what is not
  processed yet.
- A shard is owned by one worker at a time through a lease
  (``SET locus:lease:<n> <worker> NX PX``), renewed while the worker lives. A
  worker takes at most its fair share (shards / live workers); shards of a
  worker that stops renewing are taken by the others, which first re-process
  the entries the dead consumer left pending (``XAUTOCLAIM``), resuming each
  device from its snapshot in Redis.
- Results (acknowledgements with positions, zone events) go to every API node
  through the pub/sub channel ``locus:results``; each node resolves its own
  ``?wait=true`` requests and feeds its WebSocket subscribers.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
import uuid
from collections import deque
from typing import Any

import redis

from app.core.config import Settings
from app.core.db import make_engine, make_sessionmaker
from app.core.heap import PeriodicTrim, map_large_allocations, settle_heap
from app.core.outages import is_outage, retry_through_outage
from app.core.time import now_ms
from app.workers.broker import ResultHandler
from app.workers.coverage import CoverageLedger
from app.workers.messages import Ingest, Result, decode_ingest, decode_results, encode
from app.workers.process import handle_safely
from app.workers.shard import Shard
from app.workers.sites import SiteCache
from app.workers.snapshot_store import RedisSnapshots

log = logging.getLogger(__name__)

GROUP = "workers"
RESULTS = "locus:results"


def stream_key(shard: int) -> str:
    """Return the stream of a shard."""
    return f"locus:shard:{shard}"


def held_key(shard: int) -> str:
    """Return the count of a shard's processed entries that wait for a snapshot."""
    return f"locus:held:{shard}"


def lease_key(shard: int) -> str:
    """Return the lease key of a shard."""
    return f"locus:lease:{shard}"


def ensure_group(client: redis.Redis, shard: int) -> None:
    """Create the shard's stream and its consumer group unless they exist."""
    try:
        client.xgroup_create(stream_key(shard), GROUP, id="0", mkstream=True)
    except redis.ResponseError as exc:
        if "BUSYGROUP" not in str(exc):
            raise


# Renew only a lease we still hold: compare-and-pexpire.
_RENEW = """
if redis.call('get', KEYS[1]) == ARGV[1] then
  return redis.call('pexpire', KEYS[1], ARGV[2])
end
return 0
"""
_RELEASE = """
if redis.call('get', KEYS[1]) == ARGV[1] then
  return redis.call('del', KEYS[1])
end
return 0
"""


class RedisBroker:
    """The API node's side: publish batches to shard streams, receive results by pub/sub."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.shards = settings.shards
        self.client = redis.Redis.from_url(settings.broker)
        self._outgoing: deque[tuple[int, bytes]] = deque()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._down = threading.Event()
        self._backlog = [0] * self.shards
        self._owned = [False] * self.shards
        self._threads: list[threading.Thread] = []

    async def start(self, on_results: ResultHandler) -> None:
        """Start the publisher and the results listener (``on_results`` runs on this loop)."""
        loop = asyncio.get_running_loop()

        def on_loop(results: list[Result]) -> None:
            if not loop.is_closed():
                loop.call_soon_threadsafe(on_results, results)

        self._on_results = on_loop
        await asyncio.to_thread(self._start_threads)

    def _start_threads(self) -> None:
        for shard in range(self.shards):
            ensure_group(self.client, shard)
        for target, name in (
            (self._publish_loop, "redis-publish"),
            (self._listen, "redis-results"),
            (self._watch, "redis-backlog"),
        ):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def publish(self, shard: int, message: Ingest) -> None:
        """Queue the batch for the publisher thread (pipelined XADDs, off the event loop)."""
        self._outgoing.append((shard, encode(message)))
        self._backlog[shard] += 1
        self._wake.set()

    def available(self) -> bool:
        """Return whether Redis answered the last time this node spoke to it."""
        return not self._down.is_set()

    def _publish_loop(self) -> None:
        while not self._stopping.is_set():
            self._wake.wait(0.1)
            self._wake.clear()
            while self._outgoing and not self._stopping.is_set():
                batch = [self._outgoing.popleft() for _ in range(min(len(self._outgoing), 500))]
                pipe = self.client.pipeline(transaction=False)
                for shard, data in batch:
                    pipe.xadd(
                        stream_key(shard),
                        {"m": data},
                        maxlen=self.settings.stream_maxlen,
                        approximate=True,
                    )
                try:
                    pipe.execute()
                except redis.RedisError as exc:
                    # accepted batches wait here, in order, until Redis takes them
                    self._outgoing.extendleft(reversed(batch))
                    self._went_down(exc, "publishing")
                    self._stopping.wait(0.5)
                    continue
                self._down.clear()

    def _went_down(self, exc: redis.RedisError, doing: str) -> None:
        if not self._down.is_set():
            log.warning(
                "Redis unavailable while %s (%s); ingest answers 503 until it returns", doing, exc
            )
        self._down.set()

    def _listen(self) -> None:
        while not self._stopping.is_set():
            try:
                pubsub = self.client.pubsub(ignore_subscribe_messages=True)
                pubsub.subscribe(RESULTS)
                while not self._stopping.is_set():
                    item = pubsub.get_message(timeout=0.2)
                    if item is not None:
                        self._on_results(decode_results(item["data"]))
            except redis.RedisError as exc:
                self._went_down(exc, "listening for results")
                time.sleep(0.5)

    def _watch(self) -> None:
        # Backlog = entries not yet delivered (lag) + delivered and not acknowledged, less
        # those processed that wait for a snapshot (a dead worker's count lapses with it).
        while not self._stopping.wait(0.5):
            try:
                held = self.client.mget([held_key(shard) for shard in range(self.shards)])
                for shard in range(self.shards):
                    groups = self.client.xinfo_groups(stream_key(shard))
                    info = next((g for g in groups if g["name"] in (GROUP, GROUP.encode())), None)
                    if info is not None:
                        pending = max(0, int(info["pending"]) - int(held[shard] or 0))
                        self._backlog[shard] = int(info.get("lag") or 0) + pending
                    self._owned[shard] = bool(self.client.exists(lease_key(shard)))
            except redis.RedisError as exc:
                self._went_down(exc, "reading the backlog")
                continue
            if self._down.is_set() and not self._outgoing:
                log.warning("Redis is back")
                self._down.clear()

    def backlog(self, shard: int) -> int:
        """Return the shard's undelivered plus unacknowledged entries (refreshed twice a second)."""
        return self._backlog[shard]

    def healthy(self) -> bool:
        """Return whether Redis answers and every shard has an owner."""
        try:
            self.client.ping()
        except redis.RedisError:
            return False
        return all(self._owned)

    async def stop(self) -> None:
        """Flush what is queued and stop the threads."""
        await asyncio.to_thread(self._stop_threads)

    def _stop_threads(self) -> None:
        deadline = time.monotonic() + 5
        while self._outgoing and time.monotonic() < deadline:
            time.sleep(0.05)
        if self._outgoing:
            log.error("stopping with %d accepted batches Redis never took", len(self._outgoing))
        self._stopping.set()
        for thread in self._threads:
            thread.join(timeout=2)


class LocalRedisWorkers:
    """Worker processes on this node for the Redis broker (``serve --workers N --broker redis``)."""

    def __init__(self, settings: Settings, count: int) -> None:
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        self.processes = [
            ctx.Process(
                target=redis_worker_main,
                args=(settings.model_dump_json(),),
                name=f"locus-redis-worker-{i}",
                daemon=True,
            )
            for i in range(count)
        ]

    def start(self) -> None:
        """Start the processes."""
        for process in self.processes:
            process.start()

    def stop(self) -> None:
        """Ask the processes to hand their shards back and wait for them."""
        for process in self.processes:
            if process.is_alive():
                process.terminate()
        for process in self.processes:
            process.join(timeout=15)


class RedisWorker:
    """A worker node's loop: hold leases on a fair share of shards and process their streams."""

    def __init__(self, settings: Settings, *, name: str | None = None) -> None:
        self.settings = settings
        self.name = name or f"worker-{uuid.uuid4().hex[:8]}"
        self.client = redis.Redis.from_url(settings.broker)
        self.engine = make_engine(settings.resolved_database_url)
        self.sessions = make_sessionmaker(engine=self.engine)
        self.snapshots = RedisSnapshots(self.client)
        self.shards: dict[int, Shard] = {}
        self.ledgers: dict[int, CoverageLedger[bytes]] = {}
        self.sites = SiteCache(settings=settings, sessions=self.sessions)
        self.lease_ms = int(settings.lease_s * 1000)
        self._renew = self.client.register_script(_RENEW)
        self._release = self.client.register_script(_RELEASE)
        self._last_lease = 0.0
        self._last_manage = 0.0
        self._last_stats = 0.0
        self._trim = PeriodicTrim(settings.heap_trim_every_s)
        self._settle_until = 0.0

    # -- leases ------------------------------------------------------------------------

    def _live_workers(self) -> int:
        self.client.set(f"locus:worker:{self.name}", 1, px=self.lease_ms)
        return max(1, sum(1 for _ in self.client.scan_iter("locus:worker:*", count=1000)))

    def _renew_owned(self) -> None:
        """Renew the leases of the owned shards and let go of any another worker holds now.

        Run before every read: a worker stalled past its lease (a long take, a
        loaded machine) must not read entries of a shard that is no longer its own.
        """
        if not self.shards:
            return
        owned = list(self.shards)
        pipe = self.client.pipeline(transaction=False)
        for shard in owned:
            self._renew(keys=[lease_key(shard)], args=[self.name, self.lease_ms], client=pipe)
        for shard, renewed in zip(owned, pipe.execute(), strict=True):
            if renewed:
                continue
            # A lease that lapsed while Redis was away and that nobody took since is still
            # ours, and so are the devices' buffered samples: keep the shard.
            if self.client.set(lease_key(shard), self.name, nx=True, px=self.lease_ms):
                log.info("%s kept shard %d through a lapsed lease", self.name, shard)
                continue
            log.warning("%s lost shard %d", self.name, shard)
            # Another worker may run the shard already: storing positions or snapshots
            # now could overwrite its newer ones, so the devices are only let go, and
            # their unacknowledged entries are the new owner's to replay.
            self.shards.pop(shard).close()
            self.ledgers.pop(shard, None)
        self._last_lease = time.monotonic()

    def _manage_leases(self) -> None:
        """Take a fair share of the shards and hand back what is over it."""
        if self.ledgers:
            # the counts of held entries live as long as the leases do
            pipe = self.client.pipeline(transaction=False)
            for shard, ledger in self.ledgers.items():
                pipe.set(held_key(shard), len(ledger), px=self.lease_ms)
            pipe.execute()
        live = self._live_workers()
        if time.monotonic() < self._settle_until:
            # just back from a Redis outage: every worker first takes back its own shards
            return
        fair = math.ceil(self.settings.shards / live)
        for shard in range(self.settings.shards):
            if len(self.shards) >= fair:
                break
            if shard in self.shards:
                continue
            if self.client.set(lease_key(shard), self.name, nx=True, px=self.lease_ms):
                self._take(shard)
        # give back what is over the fair share so a newcomer gets work
        while len(self.shards) > fair:
            self._hand_back(max(self.shards))

    def _take(self, shard: int) -> None:
        ensure_group(self.client, shard)
        self.shards[shard] = Shard(
            shard=shard,
            settings=self.settings,
            sessions=self.sessions,
            clock=now_ms,
            snapshots=self.snapshots,
            sites=self.sites,
            on_storage_wait=self._keep_leases,
        )
        self.ledgers[shard] = CoverageLedger()
        # entries a previous owner read but no snapshot of its held are ours, oldest first
        claimed = 0
        cursor = "0-0"
        while True:
            cursor, entries, _ = self.client.xautoclaim(
                stream_key(shard), GROUP, self.name, min_idle_time=0, start_id=cursor, count=500
            )
            if entries:
                claimed += len(entries)
                self._process(shard, entries)
            if cursor in (b"0-0", "0-0") or not entries:
                break
        log.info("%s took shard %d (%d pending entries re-processed)", self.name, shard, claimed)

    # -- processing ------------------------------------------------------------------

    def _keep_leases(self) -> None:
        """Renew the held leases while a shard waits out a database outage, so that no other
        worker takes a shard whose batches this one is still holding."""
        if time.monotonic() - self._last_lease < self.settings.lease_s / 3:
            return
        try:
            for shard in self.shards:
                self._renew(keys=[lease_key(shard)], args=[self.name, self.lease_ms])
        except redis.RedisError:
            return  # Redis is away too: the loop sorts the leases out when it is back
        self._last_lease = time.monotonic()

    def _process(self, shard: int, entries: list[Any]) -> None:
        # a long round (a take's backlog, a loaded machine) must not let the leases lapse
        self._keep_leases()
        # an entry without fields was trimmed from the stream before it was claimed
        acked = [entry_id for entry_id, fields in entries if not fields]
        kept = [(entry_id, decode_ingest(fields[b"m"])) for entry_id, fields in entries if fields]
        messages = [message for _, message in kept]
        results = handle_safely(self.shards[shard], messages) if messages else []
        ledger = self.ledgers[shard]
        acked += ledger.hold_batches(
            self.shards[shard], [entry_id for entry_id, _ in kept], messages, results
        )
        self._report(shard, list(results), acked)

    def _report(self, shard: int, results: list[Result], acked: list[Any]) -> None:
        """Publish results and acknowledge the entries stored snapshots now hold."""
        acked = acked + self.ledgers[shard].release(self.shards[shard].newly_covered())
        held = len(self.ledgers[shard])

        def report() -> None:
            pipe = self.client.pipeline(transaction=False)
            if results:
                pipe.publish(RESULTS, encode(results))
            if acked:
                pipe.xack(stream_key(shard), GROUP, *acked)
            pipe.set(held_key(shard), held, px=self.lease_ms)
            pipe.execute()

        # the positions are stored: acknowledge once Redis is back (an entry left pending
        # would be processed again, its positions suppressed as repeats)
        retry_through_outage(report, what=f"{self.name}: acknowledging", on_wait=self._keep_leases)

    def _hand_back(self, shard_id: int) -> None:
        """Drain the shard (its devices snapshotted for the next owner) and release its lease."""
        drained = self.shards[shard_id]
        results: list[Result] = list(drained.drain())
        drained.newly_covered()
        self._report(shard_id, results, self.ledgers[shard_id].release_all())
        del self.shards[shard_id], self.ledgers[shard_id]
        self._release(keys=[lease_key(shard_id)], args=[self.name])

    def run(self, stop: threading.Event) -> None:
        """Process until ``stop`` is set, then flush and hand the shards back."""
        # every site built before taking a shard: a new device's first batch must not wait
        self.sites.poll(wait=True)
        log.info("%s started", self.name)
        down_since: float | None = None
        while not stop.is_set():
            try:
                self._round(stop)
            except redis.RedisError as exc:
                if not is_outage(exc) and "NOGROUP" not in str(exc):
                    raise
                if down_since is None:
                    down_since = time.monotonic()
                    log.warning("%s: Redis unavailable (%s); waiting for it", self.name, exc)
                # leases lapse meanwhile: on its return, a worker takes back its own first
                self._settle_until = math.inf
                stop.wait(0.5)
                continue
            if down_since is not None:
                log.warning("%s: Redis back after %.1f s", self.name, time.monotonic() - down_since)
                down_since = None
                self._settle_until = time.monotonic() + self.settings.lease_s
        for shard_id in list(self.shards):
            self._hand_back(shard_id)
        self.client.delete(f"locus:worker:{self.name}")
        self.sites.close()
        self.engine.dispose()

    def _round(self, stop: threading.Event) -> None:
        """Rebalance shards when due, renew the leases, process what the owned streams hold,
        flush quiet devices."""
        self.sites.poll()
        if time.monotonic() - self._last_manage >= self.settings.lease_s / 3:
            self._manage_leases()
            self._last_manage = time.monotonic()
        self._renew_owned()
        if not self.shards:
            stop.wait(0.2)
            return
        streams: dict[Any, Any] = {stream_key(s): ">" for s in self.shards}
        try:
            response: Any = self.client.xreadgroup(GROUP, self.name, streams, count=500, block=50)
        except redis.ResponseError as exc:
            if "NOGROUP" in str(exc):
                # Redis came back without its data: the streams start again
                for shard in self.shards:
                    ensure_group(self.client, shard)
            raise
        for key, entries in response or ():
            name = key.decode() if isinstance(key, bytes) else key
            shard_id = int(name.rsplit(":", 1)[1])
            if shard_id in self.shards:
                self._process(shard_id, entries)
        for shard_id, owned in self.shards.items():
            emitted: list[Result] = list(owned.tick())
            if emitted or owned.has_newly_covered():
                self._report(shard_id, emitted, [])
        if time.monotonic() - self._last_stats >= 1.0:
            stats = [shard.stats() for shard in self.shards.values()]
            self._last_stats = time.monotonic()
            if stats:
                self.client.publish(RESULTS, encode(stats))
        self._trim()


def redis_worker_main(settings_json: str) -> None:
    """Entry point of a worker process on the Redis broker (SIGTERM stops it cleanly)."""
    import signal

    from app.core.logging import configure_logging

    configure_logging()
    settings = Settings.model_validate_json(settings_json)
    map_large_allocations(settings.worker_mmap_threshold_bytes)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    worker = RedisWorker(settings)
    settle_heap()
    worker.run(stop)
