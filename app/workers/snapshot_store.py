"""Where device snapshots live: the database (embedded default) or Redis (multi-node)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, cast

from sqlalchemy.orm import Session

from app.devices.models import DeviceStateRecord

if TYPE_CHECKING:
    from redis import Redis


class SnapshotStore(Protocol):
    """Load and save a device's latest snapshot."""

    def load(self, db: Session, device_id: str) -> tuple[str, bytes] | None:
        """Return (site_id, snapshot bytes) or None."""
        ...

    def save(self, db: Session, device_id: str, site_id: str, t: int, blob: bytes) -> None:
        """Store the snapshot taken at measurement time ``t``."""
        ...


class DatabaseSnapshots:
    """Snapshots in the ``device_states`` table, written in the shard's transaction."""

    def load(self, db: Session, device_id: str) -> tuple[str, bytes] | None:
        """Return the stored snapshot of the device."""
        row = db.get(DeviceStateRecord, device_id)
        return None if row is None else (row.site_id, row.snapshot)

    def save(self, db: Session, device_id: str, site_id: str, t: int, blob: bytes) -> None:
        """Insert or replace the device's snapshot."""
        row = db.get(DeviceStateRecord, device_id)
        if row is None:
            db.add(DeviceStateRecord(device_id=device_id, site_id=site_id, t=t, snapshot=blob))
        else:
            row.site_id, row.t, row.snapshot = site_id, t, blob


class RedisSnapshots:
    """Snapshots in Redis hashes ``locus:snap:<device>``, shared by every worker node."""

    def __init__(self, client: Redis, ttl_s: int = 7 * 24 * 3600) -> None:
        self.client = client
        self.ttl_s = ttl_s

    def load(self, db: Session, device_id: str) -> tuple[str, bytes] | None:
        """Return the device's snapshot from Redis."""
        # the client answers bytes (no decode_responses): the blob is binary
        entry = cast(dict[bytes, bytes], self.client.hgetall(f"locus:snap:{device_id}"))
        if not entry:
            return None
        return entry[b"site"].decode(), entry[b"blob"]

    def save(self, db: Session, device_id: str, site_id: str, t: int, blob: bytes) -> None:
        """Write the snapshot (expiring after a week of silence)."""
        key = f"locus:snap:{device_id}"
        pipe = self.client.pipeline()
        pipe.hset(key, mapping={"site": site_id, "t": t, "blob": blob})
        pipe.expire(key, self.ttl_s)
        pipe.execute()
