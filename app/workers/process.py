"""The filter worker process: drain its inbox, process, report results and stats."""

from __future__ import annotations

import contextlib
import logging
import signal
import time
from multiprocessing.connection import Connection
from typing import Any

from app.core.config import Settings
from app.core.db import make_engine, make_sessionmaker
from app.core.heap import PeriodicTrim, map_large_allocations, settle_heap
from app.core.logging import configure_logging
from app.core.time import now_ms
from app.workers.coverage import CoverageLedger
from app.workers.messages import Acked, Done, Ingest, Ready, Result, Stop, decode_inbound, encode
from app.workers.pipes import Inbox, send
from app.workers.shard import Shard
from app.workers.sites import SiteCache

log = logging.getLogger(__name__)


def _drain(inbox: Inbox, timeout: float, most: int, linger: float) -> list[bytes]:
    """Return the messages waiting in the inbox, waiting up to ``timeout`` for the first
    and then up to ``linger`` seconds for more; take at most ``most`` messages."""
    messages = inbox.take(timeout, most)
    if not messages:
        return []
    until = time.monotonic() + linger
    while len(messages) < most:
        more = inbox.take(max(until - time.monotonic(), 0.0), most - len(messages))
        if not more:
            break
        messages.extend(more)
    return messages


def handle_safely(shard: Shard, messages: list[Ingest]) -> list[Done]:
    """Process a drained group; if it fails, retry one by one so one bad batch fails alone."""
    try:
        return shard.handle(messages)
    except Exception:
        log.exception("shard %d: group of %d failed, retrying singly", shard.shard, len(messages))
    results = []
    for msg in messages:
        try:
            results.extend(shard.handle([msg]))
        except Exception as exc:
            log.exception("shard %d: batch %s failed", shard.shard, msg.batch_id)
            shard.counters["failed_batches"] += 1
            results.append(Done(msg.batch_id, msg.site_id, msg.device_id, error=str(exc)))
    return results


def worker_main(shard_id: int, settings_json: str, inbox: Connection, outbox: Connection) -> None:
    """Run one shard until a stop message, SIGTERM or the API closing the inbox.

    Batches come in on ``inbox`` and results go out on ``outbox``, the ends of two pipes
    whose other ends the API holds (``app.workers.pipes`` frames both).
    """
    settings = Settings.model_validate_json(settings_json)
    map_large_allocations(settings.worker_mmap_threshold_bytes)
    configure_logging()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    stopping = False

    def _terminate(*_: Any) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, _terminate)
    engine = make_engine(settings.resolved_database_url)
    sessions = make_sessionmaker(engine)
    sites = SiteCache(settings=settings, sessions=sessions)
    # ready once every site is built: a new device's first batch must not wait for rasters
    sites.poll(wait=True)
    shard = Shard(shard=shard_id, settings=settings, sessions=sessions, clock=now_ms, sites=sites)
    settle_heap()
    send(outbox, encode([Ready(shard_id)]))
    batches = Inbox(inbox)
    ledger: CoverageLedger[str] = CoverageLedger()
    last_stats = time.monotonic()
    trim = PeriodicTrim(settings.heap_trim_every_s)
    while not stopping:
        drained = _drain(
            batches,
            timeout=0.05,
            most=settings.worker_max_messages,
            linger=settings.worker_linger_ms / 1000,
        )
        inbound = [decode_inbound(data) for data in drained]
        stopping = stopping or batches.closed or any(isinstance(m, Stop) for m in inbound)
        messages = [m for m in inbound if isinstance(m, Ingest)]
        out: list[Result] = []
        acked: list[str] = []
        if messages:
            done = handle_safely(shard, messages)
            out += done
            acked += ledger.hold_batches(shard, [m.batch_id for m in messages], messages, done)
        out += shard.tick()
        acked += ledger.release(shard.newly_covered())
        if acked:
            out.append(Acked(acked))
        if time.monotonic() - last_stats >= settings.worker_stats_every_s:
            out.append(shard.stats())
            last_stats = time.monotonic()
        trim()
        try:
            if out:
                send(outbox, encode(out))
        except BrokenPipeError:
            log.warning("shard %d: the API is gone; stopping", shard_id)
            stopping = True
        sites.poll()
    # the devices' snapshots are written even when nobody reads the last results
    emitted = shard.drain()
    shard.newly_covered()
    with contextlib.suppress(BrokenPipeError):
        send(outbox, encode([*emitted, Acked(ledger.release_all()), shard.stats()]))
    sites.close()
    engine.dispose()
