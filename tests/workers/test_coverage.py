"""A batch is acknowledged only once a stored snapshot holds it, so a worker that dies
mid-stream loses none of the samples its devices were holding: the next one replays
what was not acknowledged on top of the last snapshot and stores every window."""

from __future__ import annotations

import threading
import uuid
from pathlib import Path

import pytest
import redis
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.db import session_scope
from app.positions.models import PositionRecord
from app.sites.assembly import LoadedSite
from app.workers.coverage import CoverageLedger
from app.workers.messages import Ingest, encode
from app.workers.redis_broker import GROUP, RedisWorker, held_key, lease_key, stream_key
from app.workers.shard import Shard
from tests.workers.conftest import REDIS_URL, SITE_ID
from tests.workers.office import Clock, per_second, uwb_ranges

SNAPSHOT_EVERY_MS = 4000
CRASH_AFTER = 9
"""Uploads the first worker takes before it dies: past one snapshot, with samples held."""


@pytest.fixture
def settings(office_url: str, tmp_path: Path) -> Settings:
    return Settings(
        database_url=office_url,
        home=tmp_path,
        snapshot_every_ms=SNAPSHOT_EVERY_MS,
        flush_after_s=2.5,
        idle_evict_s=60,
    )


def _messages(office: LoadedSite, device_id: str, seconds: int = 14) -> list[Ingest]:
    return [
        Ingest(uuid.uuid4().hex, SITE_ID, device_id, office.version, {"uwb": samples})
        for samples in per_second(uwb_ranges(seconds))
    ]


def _stored(sessions: sessionmaker[Session], device_id: str) -> list[int]:
    with session_scope(sessions) as db:
        query = select(PositionRecord.t).where(
            PositionRecord.site_id == SITE_ID,
            PositionRecord.device_id == device_id,
            PositionRecord.smoothed.is_(False),
        )
        return sorted(db.scalars(query))


def _run(shard: Shard, ledger: CoverageLedger[str], messages: list[Ingest]) -> list[str]:
    """Process messages one per round as a worker does; return the batch ids acknowledged."""
    acked: list[str] = []
    for message in messages:
        done = shard.handle([message])
        acked += ledger.hold_batches(shard, [message.batch_id], [message], done)
        acked += ledger.release(shard.newly_covered())
    return acked


def test_a_batch_is_acknowledged_only_once_a_stored_snapshot_holds_it(
    settings: Settings, office_sessions: sessionmaker[Session], office: LoadedSite
) -> None:
    # a fixed id, so a fixed phase of the snapshot period: its last periodic snapshot falls
    # before the walk's last batches
    messages = _messages(office, "held-tag-a")
    shard = Shard(shard=0, settings=settings, sessions=office_sessions, clock=Clock())
    ledger: CoverageLedger[str] = CoverageLedger()

    acked = _run(shard, ledger, messages)

    (device,) = shard.devices.values()
    ids = [m.batch_id for m in messages]
    assert device.snapshot_t >= 0, "a periodic snapshot was stored"
    assert acked == ids[: device.covered], "exactly the batches the snapshot holds, in order"
    assert 0 < len(ledger) == len(ids) - device.covered, "the newest batches are still held"
    held = ids[device.covered :]
    shard.drain()
    shard.newly_covered()
    assert ledger.release_all() == held
    assert len(ledger) == 0


def test_a_device_gone_quiet_is_snapshotted_and_its_batches_acknowledged(
    settings: Settings, office_sessions: sessionmaker[Session], office: LoadedSite
) -> None:
    clock = Clock()
    # no periodic snapshot after its first: the batches since wait for its flush
    rare = settings.model_copy(update={"snapshot_every_ms": 3_600_000})
    shard = Shard(shard=0, settings=rare, sessions=office_sessions, clock=clock)
    ledger: CoverageLedger[str] = CoverageLedger()
    messages = _messages(office, f"quiet-{uuid.uuid4().hex[:8]}", seconds=8)
    acked = _run(shard, ledger, messages)
    assert len(ledger) > 0

    clock.advance(settings.flush_after_s)
    shard.tick()
    acked += ledger.release(shard.newly_covered())

    assert acked == [m.batch_id for m in messages] and len(ledger) == 0


def test_the_next_worker_replays_what_was_not_acknowledged_and_stores_every_window(
    settings: Settings, office_sessions: sessionmaker[Session], office: LoadedSite
) -> None:
    clock = Clock()
    # fixed ids, fixed phases of the snapshot period: the crashed device's last periodic
    # snapshot falls before its worker dies
    reference, crashed = "ref-walk", "crashed-walk-a"
    whole = Shard(shard=0, settings=settings, sessions=office_sessions, clock=clock)
    _run(whole, CoverageLedger(), _messages(office, reference))
    whole.drain()

    messages = _messages(office, crashed)
    dying = Shard(shard=0, settings=settings, sessions=office_sessions, clock=clock)
    acked = set(_run(dying, CoverageLedger(), messages[:CRASH_AFTER]))
    assert next(iter(dying.devices.values())).buffer, "the dying worker held samples"
    # it dies: nothing drained, nothing more stored; the broker re-delivers the rest
    redelivered = [m for m in messages if m.batch_id not in acked]
    assert redelivered[0] is not messages[CRASH_AFTER], "held batches are delivered again"
    nxt = Shard(shard=0, settings=settings, sessions=office_sessions, clock=clock)
    _run(nxt, CoverageLedger(), redelivered)
    nxt.drain()

    whole_walk = _stored(office_sessions, reference)
    offset = [t - whole_walk[0] for t in whole_walk]
    got = _stored(office_sessions, crashed)
    assert [t - got[0] for t in got] == offset, "every window of the walk is stored once"
    assert nxt.counters["restored"] == 1


def _stream(client: redis.Redis, worker: RedisWorker, messages: list[Ingest]) -> None:
    """Publish the batches one a round, as devices uploading every second are read."""
    stop = threading.Event()
    worker._round(stop)  # takes the shard
    for message in messages:
        client.xadd(stream_key(0), {"m": encode(message)})
        worker._round(stop)


def test_a_redis_worker_killed_mid_stream_leaves_its_held_entries_to_the_next(
    settings: Settings,
    office_sessions: sessionmaker[Session],
    office: LoadedSite,
    redis_client: redis.Redis,
) -> None:
    redis_client.flushdb()
    config = settings.model_copy(update={"broker": REDIS_URL, "shards": 1, "lease_s": 1.0})
    device = "redis-walk-a"  # a fixed phase, as above
    messages = _messages(office, device)
    first = RedisWorker(config, name="first")
    first.sites.poll(wait=True)
    _stream(redis_client, first, messages[:CRASH_AFTER])
    pending = redis_client.xpending(stream_key(0), GROUP)["pending"]
    assert pending > 0, "entries the last snapshot does not hold stay unacknowledged"
    assert int(redis_client.get(held_key(0)) or 0) == pending, "and are counted as held"

    # killed: it renews nothing more; once its lease is gone the next worker takes over
    redis_client.delete(lease_key(0), "locus:worker:first")
    second = RedisWorker(config, name="second")
    second.sites.poll(wait=True)
    _stream(redis_client, second, messages[CRASH_AFTER:])
    second._hand_back(0)

    got = _stored(office_sessions, device)
    steps = {b - a for a, b in zip(got, got[1:], strict=False)}
    assert len(steps) == 1, f"every window stored once, none missing: steps {steps}"
    assert got[-1] >= messages[-1].samples["uwb"][-1]["t"] - steps.pop()
    assert redis_client.xpending(stream_key(0), GROUP)["pending"] == 0, "handed back: all acked"
    first.sites.close()
    second.sites.close()
