"""Which shard owns a device: a stable hash, the same in every process and every run."""

from __future__ import annotations

import hashlib


def shard_of(device_id: str, shards: int) -> int:
    """Return the shard (0 … shards-1) that owns ``device_id``."""
    digest = hashlib.blake2b(device_id.encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") % shards
