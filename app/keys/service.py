"""Creating and resolving API keys."""

from __future__ import annotations

import time

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.security import Principal, Role, hash_key, new_key
from app.keys.models import ApiKey

_CACHE_TTL_S = 30.0
_cache: dict[str, tuple[float, Principal | None]] = {}


def create_key(*, db: Session, role: Role, site_id: str | None, label: str | None) -> str:
    """Store a new key's hash and return the key itself (shown once)."""
    key = new_key()
    db.add(ApiKey(key_hash=hash_key(key), role=role, site_id=site_id, label=label))
    db.flush()
    return key


def ensure_key(*, db: Session, key: str, role: Role, label: str) -> bool:
    """Store ``key`` if it is not stored yet; return whether it was added."""
    digest = hash_key(key)
    if db.scalar(select(ApiKey.id).where(ApiKey.key_hash == digest)) is not None:
        return False
    db.add(ApiKey(key_hash=digest, role=role, site_id=None, label=label))
    db.flush()
    return True


def has_admin(*, db: Session) -> bool:
    """Return whether any admin key exists."""
    return db.scalar(select(ApiKey.id).where(ApiKey.role == "admin").limit(1)) is not None


def cached_key(key: str) -> tuple[bool, Principal | None]:
    """Return (cached?, principal or None for a key known to be unknown) without the database."""
    hit = _cache.get(hash_key(key))
    if hit is not None and time.monotonic() - hit[0] < _CACHE_TTL_S:
        return True, hit[1]
    return False, None


def resolve_key(*, db: Session, key: str) -> Principal | None:
    """Return the principal of a key, or None if unknown, and cache it briefly."""
    digest = hash_key(key)
    now = time.monotonic()
    row = db.scalar(select(ApiKey).where(ApiKey.key_hash == digest))
    principal = Principal(role=row.role, site_id=row.site_id) if row else None  # type: ignore[arg-type]
    if len(_cache) > 10_000:
        _cache.clear()
    _cache[digest] = (now, principal)
    return principal
