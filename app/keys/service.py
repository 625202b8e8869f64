"""Creating and resolving API keys."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.security import Principal, Role, hash_key, new_key
from app.keys.models import ApiKey


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


def resolve_key(*, db: Session, key: str) -> Principal | None:
    """Return the principal of a key, or None if unknown."""
    row = db.scalar(select(ApiKey).where(ApiKey.key_hash == hash_key(key)))
    return Principal(role=row.role, site_id=row.site_id) if row else None  # type: ignore[arg-type]
