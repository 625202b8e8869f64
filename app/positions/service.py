"""Reading stored positions of one device of one site."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import cache
from typing import Any

from sqlalchemy import Select, Table, func, or_, select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session
from sqlalchemy.sql.expression import Executable

from app.engine.samples import Estimate
from app.engine.smoothing import SmootherParams, smooth_track
from app.positions.models import PositionRecord


def store(db: Session, rows: Sequence[Mapping[str, Any]]) -> None:
    """Insert position rows, skipping any already stored for its device, time and kind.

    A batch can be positioned twice (re-delivered after its worker died, or run
    by a worker that lost its shard mid-round): the history keeps one of each.
    """
    if not rows:
        return
    db.execute(_insert(db.get_bind().dialect.name), list(rows))


@cache
def _insert(dialect_name: str) -> Executable:
    """Return the insert of position rows as a Core statement on the table, built once.

    The ORM's bulk insert (the statement on the mapped class) costs a worker's
    small rounds several times more than the statement on the table.
    """
    dialect = postgresql if dialect_name == "postgresql" else sqlite
    table = PositionRecord.__table__
    assert isinstance(table, Table)
    return dialect.insert(table).on_conflict_do_nothing()


def latest(*, db: Session, site_id: str, device_id: str) -> PositionRecord | None:
    """Return the device's live position with the greatest measurement time."""
    query = select(PositionRecord).where(
        PositionRecord.site_id == site_id,
        PositionRecord.device_id == device_id,
        PositionRecord.smoothed.is_(False),
    )
    return db.scalar(query.order_by(PositionRecord.t.desc(), PositionRecord.id.desc()).limit(1))


def latest_of(*, db: Session, site_id: str, device_ids: Sequence[str]) -> dict[str, PositionRecord]:
    """Return the latest live position of each of the site's ``device_ids`` that has one."""
    if not device_ids:
        return {}
    ranked = (
        select(
            PositionRecord.id,
            func.row_number()
            .over(
                partition_by=PositionRecord.device_id,
                order_by=(PositionRecord.t.desc(), PositionRecord.id.desc()),
            )
            .label("rank"),
        )
        .where(
            PositionRecord.site_id == site_id,
            PositionRecord.device_id.in_(device_ids),
            PositionRecord.smoothed.is_(False),
        )
        .subquery()
    )
    query = select(PositionRecord).join(ranked, ranked.c.id == PositionRecord.id)
    rows = db.scalars(query.where(ranked.c.rank == 1))
    return {row.device_id: row for row in rows}


def history(
    *, db: Session, site_id: str, device_id: str, t_from: int | None, t_to: int | None, limit: int
) -> list[PositionRecord]:
    """Return up to ``limit`` positions with ``t_from <= t <= t_to``, ascending t.

    Refined positions are preferred (:func:`history_query`).
    """
    return _page(db, history_query(site_id=site_id, device_id=device_id), t_from, t_to, limit)


def history_query(*, site_id: str, device_id: str) -> Select[PositionRecord]:
    """Return the query of a device's history, unordered and unbounded.

    Refined positions are preferred: up to the last refined time the history
    holds the refined positions, after it the live ones (one per time).
    """
    own = (PositionRecord.site_id == site_id, PositionRecord.device_id == device_id)
    refined_until = (
        select(func.max(PositionRecord.t))
        .where(*own, PositionRecord.smoothed.is_(True))
        .scalar_subquery()
    )
    return select(PositionRecord).where(
        *own,
        or_(
            PositionRecord.smoothed.is_(True),
            refined_until.is_(None),
            PositionRecord.t > refined_until,
        ),
    )


def _page(
    db: Session,
    query: Select[PositionRecord],
    t_from: int | None,
    t_to: int | None,
    limit: int,
) -> list[PositionRecord]:
    """Return up to ``limit`` rows of ``query`` with ``t_from <= t <= t_to``, ascending t."""
    if t_from is not None:
        query = query.where(PositionRecord.t >= t_from)
    if t_to is not None:
        query = query.where(PositionRecord.t <= t_to)
    return list(db.scalars(query.order_by(PositionRecord.t, PositionRecord.id).limit(limit)))


def live_history(
    *, db: Session, site_id: str, device_id: str, t_from: int | None, t_to: int | None, limit: int
) -> list[PositionRecord]:
    """Return up to ``limit`` live positions with ``t_from <= t <= t_to``, ascending t."""
    query = select(PositionRecord).where(
        PositionRecord.site_id == site_id,
        PositionRecord.device_id == device_id,
        PositionRecord.smoothed.is_(False),
    )
    return _page(db, query, t_from, t_to, limit)


def full_pass(
    rows: Sequence[PositionRecord], params: SmootherParams | None = None
) -> list[tuple[float, float]]:
    """Return each live position refined by the full backward pass over ``rows`` (x, y in m).

    The positions are weighed against the odometry stored with them and
    against each other, floor run by floor run (``smooth_track``).
    """
    floors: dict[str | None, int] = {}
    estimates = [
        Estimate(
            t=r.t,
            x=r.x,
            y=r.y,
            z=r.z,
            floor=floors.setdefault(r.floor_id, len(floors)),
            heading=float("nan"),
            accuracy=r.accuracy,
            speed=float("nan"),
            method=r.method,
            odometry=None
            if r.odometry_x is None or r.odometry_y is None
            else (r.odometry_x, r.odometry_y),
        )
        for r in rows
    ]
    return [(e.x, e.y) for e in smooth_track(estimates, params or SmootherParams())]
