"""Which shard owns a device: a stable hash, the same in every process and every run."""

from __future__ import annotations

import hashlib

from app.core.identity import DeviceKey


def shard_of(key: DeviceKey, shards: int) -> int:
    """Return the shard (0 … shards-1) that owns the device ``key`` = (site, device)."""
    site_id, device_id = key
    # '/' appears in neither kind of id, so no two keys hash the same text
    digest = hashlib.blake2b(f"{site_id}/{device_id}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") % shards
