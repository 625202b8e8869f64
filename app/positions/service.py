"""Reading stored positions."""

from __future__ import annotations

from sqlalchemy import func, or_, select
from sqlalchemy.orm import Session

from app.positions.models import PositionRecord


def latest(*, db: Session, device_id: str) -> PositionRecord | None:
    """Return the device's live position with the greatest measurement time."""
    query = select(PositionRecord).where(
        PositionRecord.device_id == device_id, PositionRecord.smoothed.is_(False)
    )
    return db.scalar(query.order_by(PositionRecord.t.desc(), PositionRecord.id.desc()).limit(1))


def history(
    *, db: Session, device_id: str, t_from: int | None, t_to: int | None, limit: int
) -> list[PositionRecord]:
    """Return up to ``limit`` positions with ``t_from <= t <= t_to``, ascending t.

    Refined positions are preferred: up to the last refined time the history
    holds the refined positions, after it the live ones (one per time).
    """
    refined_until = (
        select(func.max(PositionRecord.t))
        .where(PositionRecord.device_id == device_id, PositionRecord.smoothed.is_(True))
        .scalar_subquery()
    )
    query = select(PositionRecord).where(
        PositionRecord.device_id == device_id,
        or_(
            PositionRecord.smoothed.is_(True),
            refined_until.is_(None),
            PositionRecord.t > refined_until,
        ),
    )
    if t_from is not None:
        query = query.where(PositionRecord.t >= t_from)
    if t_to is not None:
        query = query.where(PositionRecord.t <= t_to)
    return list(db.scalars(query.order_by(PositionRecord.t, PositionRecord.id).limit(limit)))


def device_site(*, db: Session, device_id: str) -> str | None:
    """Return the site the device last reported a position in."""
    pos = latest(db=db, device_id=device_id)
    return None if pos is None else pos.site_id
