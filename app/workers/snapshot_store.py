"""Where device snapshots live: the database (embedded default) or Redis (multi-node).

Snapshots are keyed by (site, device): the same device id in two sites has two.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, cast

from sqlalchemy.orm import Session

from app.core.identity import DeviceKey
from app.devices.models import DeviceStateRecord

if TYPE_CHECKING:
    from redis import Redis


class SnapshotStore(Protocol):
    """Load and save a device's latest snapshot."""

    def load(self, db: Session, key: DeviceKey) -> bytes | None:
        """Return the snapshot bytes of the device (site, device), or None."""
        ...

    def save(self, db: Session, key: DeviceKey, t: int, blob: bytes) -> None:
        """Store the snapshot taken at measurement time ``t``."""
        ...


class DatabaseSnapshots:
    """Snapshots in the ``device_states`` table, written in the shard's transaction."""

    def load(self, db: Session, key: DeviceKey) -> bytes | None:
        """Return the stored snapshot of the device."""
        row = db.get(DeviceStateRecord, key)
        return None if row is None else row.snapshot

    def save(self, db: Session, key: DeviceKey, t: int, blob: bytes) -> None:
        """Insert or replace the device's snapshot."""
        row = db.get(DeviceStateRecord, key)
        if row is None:
            db.add(DeviceStateRecord(site_id=key[0], device_id=key[1], t=t, snapshot=blob))
        else:
            row.t, row.snapshot = t, blob


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

    def save(self, db: Session, key: DeviceKey, t: int, blob: bytes) -> None:
        """Write the snapshot (expiring after a week of silence)."""
        name = redis_snapshot_key(key)
        pipe = self.client.pipeline()
        pipe.hset(name, mapping={"site": key[0], "t": t, "blob": blob})
        pipe.expire(name, self.ttl_s)
        pipe.execute()
