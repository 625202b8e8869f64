"""Where device snapshots live: the database (embedded default) or Redis (multi-node).

Snapshots are keyed by (site, device): the same device id in two sites has two.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache
from typing import TYPE_CHECKING, Protocol, cast

from sqlalchemy import Table
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session
from sqlalchemy.sql.expression import Executable

from app.core.identity import DeviceKey
from app.devices.models import DeviceStateRecord

if TYPE_CHECKING:
    from redis import Redis


class SnapshotStore(Protocol):
    """Load and save a device's latest snapshot."""

    def load(self, db: Session, key: DeviceKey) -> bytes | None:
        """Return the snapshot bytes of the device (site, device), or None."""
        ...

    def save_all(self, db: Session, snapshots: Sequence[tuple[DeviceKey, int, bytes]]) -> None:
        """Store each (device, measurement time ``t`` of the snapshot, snapshot bytes)."""
        ...


class DatabaseSnapshots:
    """Snapshots in the ``device_states`` table, written in the shard's transaction."""

    def load(self, db: Session, key: DeviceKey) -> bytes | None:
        """Return the stored snapshot of the device."""
        row = db.get(DeviceStateRecord, key)
        return None if row is None else row.snapshot

    def save_all(self, db: Session, snapshots: Sequence[tuple[DeviceKey, int, bytes]]) -> None:
        """Insert or replace the devices' snapshots: one upsert for the round (the ORM's
        read-then-write cost a saturated worker a visible share of its time; ``python -m
        bench.worker --profile`` shows what a round's snapshots cost)."""
        if snapshots:
            rows = [
                {"site_id": site, "device_id": device, "t": t, "snapshot": blob}
                for (site, device), t, blob in snapshots
            ]
            db.execute(_upsert(db.get_bind().dialect.name), rows)


@cache
def _upsert(dialect_name: str) -> Executable:
    """Return the snapshot upsert, a Core statement compiled once for any number of rows."""
    dialect = postgresql if dialect_name == "postgresql" else sqlite
    table = DeviceStateRecord.__table__
    assert isinstance(table, Table)
    statement = dialect.insert(table)
    return statement.on_conflict_do_update(
        index_elements=[table.c.site_id, table.c.device_id],
        set_={
            "t": statement.excluded.t,
            "snapshot": statement.excluded.snapshot,
            "updated_at": statement.excluded.updated_at,
        },
    )


def redis_snapshot_key(key: DeviceKey) -> str:
    """Return the Redis hash of a device's snapshot (``/`` appears in no id)."""
    return f"locus:snap:{key[0]}/{key[1]}"


class RedisSnapshots:
    """Snapshots in Redis hashes ``locus:snap:<site>/<device>``, shared by every worker node.

    A hash written before devices were keyed by site (``locus:snap:<device>``, naming its
    site inside) is still read for that site, so no device loses its state on the upgrade.
    """

    def __init__(self, client: Redis, ttl_s: int = 7 * 24 * 3600) -> None:
        self.client = client
        self.ttl_s = ttl_s

    def load(self, db: Session, key: DeviceKey) -> bytes | None:
        """Return the device's snapshot from Redis."""
        # the client answers bytes (no decode_responses): the blob is binary
        entry = cast(dict[bytes, bytes], self.client.hgetall(redis_snapshot_key(key)))
        if entry:
            return entry[b"blob"]
        legacy = cast(dict[bytes, bytes], self.client.hgetall(f"locus:snap:{key[1]}"))
        if legacy and legacy.get(b"site") == key[0].encode():
            return legacy[b"blob"]
        return None

    def save_all(self, db: Session, snapshots: Sequence[tuple[DeviceKey, int, bytes]]) -> None:
        """Write the snapshots (each expiring after a week of silence) in one round trip."""
        pipe = self.client.pipeline()
        for key, t, blob in snapshots:
            name = redis_snapshot_key(key)
            pipe.hset(name, mapping={"site": key[0], "t": t, "blob": blob})
            pipe.expire(name, self.ttl_s)
        pipe.execute()
