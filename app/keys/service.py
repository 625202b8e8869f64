"""Creating, resolving, listing and revoking API keys."""

from __future__ import annotations

from datetime import datetime, timedelta

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.core.errors import Conflict, NotFound
from app.core.security import Principal, Refusal, Role, hash_key, new_key
from app.core.time import utcnow
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
    """Return whether any admin key that works exists."""
    query = select(ApiKey.id).where(ApiKey.role == "admin", ApiKey.revoked_at.is_(None))
    return db.scalar(query.limit(1)) is not None


def resolve_key(*, db: Session, key: str) -> Principal | Refusal:
    """Return the principal of a key, or why it does not authenticate."""
    row = db.scalar(select(ApiKey).where(ApiKey.key_hash == hash_key(key)))
    if row is None:
        return "unknown"
    if row.revoked_at is not None:
        return "revoked"
    return Principal(role=row.role, site_id=row.site_id, key_id=row.id)  # type: ignore[arg-type]


def list_keys(
    *, db: Session, site_id: str | None, limit: int, offset: int
) -> tuple[list[ApiKey], int]:
    """Return a page of keys (of one site when ``site_id`` is given), oldest first, and the
    total."""
    query = select(ApiKey)
    if site_id is not None:
        query = query.where(ApiKey.site_id == site_id)
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = db.scalars(query.order_by(ApiKey.id).limit(limit).offset(offset)).all()
    return list(rows), total


def revoke_key(*, db: Session, key_id: int) -> ApiKey:
    """Mark the key revoked (idempotent); the last working admin key cannot be revoked."""
    row = db.get(ApiKey, key_id)
    if row is None:
        raise NotFound(f"key {key_id} not found")
    if row.revoked_at is not None:
        return row
    if row.role == "admin":
        others = select(func.count()).where(
            ApiKey.role == "admin", ApiKey.revoked_at.is_(None), ApiKey.id != key_id
        )
        if not db.scalar(others):
            raise Conflict("this is the last working admin key; create another admin key first")
    row.revoked_at = utcnow()
    db.flush()
    return row


def recently_revoked(*, db: Session, within: timedelta) -> list[tuple[int, str]]:
    """Return (id, hash) of the keys revoked in the last ``within`` (by this node's clock)."""
    since: datetime = utcnow() - within
    query = select(ApiKey.id, ApiKey.key_hash).where(ApiKey.revoked_at >= since)
    return [(int(i), str(h)) for i, h in db.execute(query)]
