"""Analytics read from the stored history: zone visits, a floor's device-seconds per cell;
and the store of zone events the workers emit."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import cache
from typing import Any

import numpy as np
from sqlalchemy import ColumnElement, Integer, Table, and_, case, cast, func, select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session
from sqlalchemy.sql.expression import Executable

from app.analytics.heatmap import Grid
from app.analytics.models import ZoneEventRecord
from app.analytics.occupancy import Visits
from app.positions.models import PositionRecord

ZONE_EVENT_FIELDS = ("site_id", "zone", "device_id", "floor_id", "event", "t")


def store_zone_events(db: Session, events: Sequence[Mapping[str, Any]]) -> None:
    """Insert zone events (the stream's messages), skipping any already stored.

    A batch processed twice emits its events twice; the history keeps one of each.
    """
    if not events:
        return
    rows = [{k: e.get(k) for k in ZONE_EVENT_FIELDS} for e in events]
    db.execute(_insert(db.get_bind().dialect.name), rows)


@cache
def _insert(dialect_name: str) -> Executable:
    """Return the insert of zone-event rows, repeats skipped, built once per dialect."""
    dialect = postgresql if dialect_name == "postgresql" else sqlite
    table = ZoneEventRecord.__table__
    assert isinstance(table, Table)
    return dialect.insert(table).on_conflict_do_nothing()


def zone_visits(
    *, db: Session, site_id: str, zone: str, t_from: int, t_to: int
) -> tuple[list[str], Visits]:
    """Return the devices and their stays inside ``zone`` within ``[t_from, t_to)``.

    A stay starts at an entry, or at ``t_from`` for a device whose last event before
    it was an entry; it ends at the exit, or, with no exit, at the device's last
    stored position (a device that stopped sending inside is not inside for ever),
    at most ``t_to``.
    """
    own = (ZoneEventRecord.site_id == site_id, ZoneEventRecord.zone == zone)
    last_before = (
        select(ZoneEventRecord.device_id, func.max(ZoneEventRecord.t).label("t"))
        .where(*own, ZoneEventRecord.t < t_from)
        .group_by(ZoneEventRecord.device_id)
        .subquery()
    )
    already = db.execute(
        select(ZoneEventRecord.device_id, ZoneEventRecord.event)
        .join(
            last_before,
            and_(
                ZoneEventRecord.device_id == last_before.c.device_id,
                ZoneEventRecord.t == last_before.c.t,
            ),
        )
        .where(*own)
    ).all()
    # an exit and an entry at one time: the device left and came back, so it is inside
    inside_at_start = {d for d, event in already if event == "enter"}
    events = db.execute(
        select(ZoneEventRecord.device_id, ZoneEventRecord.event, ZoneEventRecord.t)
        .where(*own, ZoneEventRecord.t >= t_from, ZoneEventRecord.t < t_to)
        # exits first at one time, as the workers emit them
        .order_by(ZoneEventRecord.device_id, ZoneEventRecord.t, ZoneEventRecord.event.desc())
    ).all()
    open_at: dict[str, tuple[int, bool]] = {d: (t_from, False) for d in inside_at_start}
    stays: list[tuple[str, int, int, bool]] = []
    for device, event, t in events:
        if event == "enter":
            open_at.setdefault(device, (t, True))
        elif device in open_at:
            start, entered = open_at.pop(device)
            stays.append((device, start, t, entered))
    for device, (start, entered) in open_at.items():
        last = _last_position_t(db, site_id, device)
        end = min(t_to, max(start, last if last is not None else start))
        stays.append((device, start, end, entered))
    stays = [s for s in stays if s[2] > s[1] or s[3]]
    devices = sorted({s[0] for s in stays})
    index = {d: k for k, d in enumerate(devices)}
    return devices, Visits(
        device=np.array([index[s[0]] for s in stays], dtype=np.int64),
        start=np.array([s[1] for s in stays], dtype=np.int64),
        end=np.array([s[2] for s in stays], dtype=np.int64),
        entered=np.array([s[3] for s in stays], dtype=bool),
    )


def _last_position_t(db: Session, site_id: str, device_id: str) -> int | None:
    """Return the time of the device's last live position (one index probe)."""
    return db.scalar(
        select(PositionRecord.t)
        .where(
            PositionRecord.site_id == site_id,
            PositionRecord.device_id == device_id,
            PositionRecord.smoothed.is_(False),
        )
        .order_by(PositionRecord.t.desc())
        .limit(1)
    )


def heatmap_cells(
    *,
    db: Session,
    site_id: str,
    floor_id: str,
    grid: Grid,
    t_from: int,
    t_to: int,
    cap_ms: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the cells' column, row and device-seconds the floor's live positions give.

    Each position weighs the time until its device's next position (on any floor), at
    most ``cap_ms``, clipped to ``[t_from, t_to)``; positions up to ``cap_ms`` before
    ``t_from`` count with the part of their time inside the range. The sums are made by
    the database, so only the grid's cells travel.
    """
    p = PositionRecord
    window = (
        select(
            p.floor_id,
            p.x,
            p.y,
            p.t,
            func.lead(p.t).over(partition_by=p.device_id, order_by=p.t).label("next_t"),
        )
        .where(
            p.site_id == site_id,
            p.smoothed.is_(False),
            p.t >= t_from - cap_ms,
            p.t < t_to,
        )
        .subquery()
    )
    w = window.c
    # end = min(next, t + cap, to); start = max(t, from)
    capped = case((w.next_t.is_(None) | (w.next_t > w.t + cap_ms), w.t + cap_ms), else_=w.next_t)
    end = case((capped > t_to, t_to), else_=capped)
    start = case((w.t < t_from, t_from), else_=w.t)
    (x0, y0), cell = grid.origin, grid.cell
    ny, nx = grid.shape
    dialect = db.get_bind().dialect.name
    i = _floor_div(w.x - x0, cell, dialect).label("i")
    j = _floor_div(w.y - y0, cell, dialect).label("j")
    seconds = (func.sum(end - start) / 1000.0).label("seconds")
    rows = db.execute(
        select(i, j, seconds)
        .where(
            w.floor_id == floor_id,
            end > start,
            w.x >= x0,
            w.y >= y0,
            w.x < x0 + nx * cell,
            w.y < y0 + ny * cell,
        )
        .group_by(i, j)
    ).all()
    return (
        np.array([r[0] for r in rows], dtype=np.int64),
        np.array([r[1] for r in rows], dtype=np.int64),
        np.array([r[2] for r in rows], dtype=float),
    )


def _floor_div(offset: ColumnElement[float], cell: float, dialect: str) -> ColumnElement[int]:
    """Return ⌊offset / cell⌋ for a non-negative offset, in the database's own arithmetic.

    PostgreSQL rounds a cast to integer, so it takes ``floor``; SQLite truncates, which
    for the non-negative offsets the query keeps is the floor (and needs no maths
    extension compiled in).
    """
    if dialect == "postgresql":
        return func.floor(offset / cell)
    return cast(offset / cell, Integer)
