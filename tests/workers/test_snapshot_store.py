"""Redis snapshots are keyed by (site, device); one written before that, under the device id
alone, still resumes its own site's device and no other."""

from __future__ import annotations

import uuid
from typing import cast

import redis
from sqlalchemy.orm import Session

from app.core.db import make_engine, make_sessionmaker, session_scope
from app.devices.models import DeviceStateRecord
from app.workers.snapshot_store import DatabaseSnapshots, RedisSnapshots, redis_snapshot_key

NO_DB = cast(Session, None)
"""Redis snapshots use no database session."""


def test_each_site_keeps_its_own_snapshot_of_the_same_device_id(redis_client: redis.Redis) -> None:
    store, device = RedisSnapshots(redis_client), f"tag-{uuid.uuid4().hex[:8]}"
    store.save_all(NO_DB, [(("a", device), 1, b"of a"), (("b", device), 2, b"of b")])
    assert store.load(NO_DB, ("a", device)) == b"of a"
    assert store.load(NO_DB, ("b", device)) == b"of b"
    redis_client.delete(redis_snapshot_key(("a", device)), redis_snapshot_key(("b", device)))


def test_a_snapshot_from_before_sites_resumes_only_its_own_site(redis_client: redis.Redis) -> None:
    store, device = RedisSnapshots(redis_client), f"tag-{uuid.uuid4().hex[:8]}"
    redis_client.hset(f"locus:snap:{device}", mapping={"site": "a", "t": 1, "blob": b"legacy"})
    assert store.load(NO_DB, ("a", device)) == b"legacy"
    assert store.load(NO_DB, ("b", device)) is None
    redis_client.delete(f"locus:snap:{device}")


def test_database_snapshots_are_inserted_then_replaced_in_one_round(database_url: str) -> None:
    sessions = make_sessionmaker(make_engine(database_url))
    site, device = f"s-{uuid.uuid4().hex[:8]}", "phone"
    with session_scope(sessions) as db:
        DatabaseSnapshots().save_all(db, [((site, device), 1, b"first"), ((site, "tag"), 1, b"t")])
    with session_scope(sessions) as db:
        first = db.get(DeviceStateRecord, (site, device))
        assert first is not None
        written = first.updated_at
    with session_scope(sessions) as db:
        DatabaseSnapshots().save_all(db, [((site, device), 2, b"second")])
    with session_scope(sessions) as db:
        store = DatabaseSnapshots()
        assert store.load(db, (site, device)) == b"second"
        assert store.load(db, (site, "tag")) == b"t"
        row = db.get(DeviceStateRecord, (site, device))
        assert row is not None and row.t == 2 and row.updated_at >= written
