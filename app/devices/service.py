"""The devices of a site: recorded as the workers hear them, listed with their last position."""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache

from sqlalchemy import Table, case, func, select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session
from sqlalchemy.sql.expression import Executable

from app.core.identity import DeviceKey
from app.devices.models import Device


def touch_devices(*, db: Session, heard: Sequence[tuple[DeviceKey, int]], now: int) -> None:
    """Record that the devices ``heard`` ((site, device), newest sample time) sent data at
    ``now`` (epoch ms): one upsert per round of the workers, not one query per device."""
    if not heard:
        return
    rows = [{"site_id": s, "device_id": d, "last_seen": now, "last_t": t} for (s, d), t in heard]
    db.execute(_upsert(db.get_bind().dialect.name), rows)


@cache
def _upsert(dialect_name: str) -> Executable:
    """Return the device upsert as one statement for any number of rows: compiled once and
    run with the rows as parameters, where a VALUES list of the round's length is compiled
    again every round. It is a Core statement on the table: the ORM's bulk path costs
    more than the write itself."""
    dialect = postgresql if dialect_name == "postgresql" else sqlite
    table = Device.__table__
    assert isinstance(table, Table)
    statement = dialect.insert(table)
    newer = statement.excluded.last_t > table.c.last_t
    return statement.on_conflict_do_update(
        index_elements=[table.c.site_id, table.c.device_id],
        set_={
            "last_seen": statement.excluded.last_seen,
            "last_t": case((newer, statement.excluded.last_t), else_=table.c.last_t),
        },
    )


def list_devices(*, db: Session, site_id: str, limit: int, offset: int) -> tuple[list[Device], int]:
    """Return a page of the site's devices (by id) and how many it has."""
    query = select(Device).where(Device.site_id == site_id)
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = db.scalars(query.order_by(Device.device_id).limit(limit).offset(offset)).all()
    return list(rows), total


def get_device(*, db: Session, site_id: str, device_id: str) -> Device | None:
    """Return the device of the site, or None when the site never heard it."""
    return db.get(Device, (site_id, device_id))


def sites_of(*, db: Session, device_id: str) -> list[str]:
    """Return the sites that have a device of this id (for the paths that name no site)."""
    query = select(Device.site_id).where(Device.device_id == device_id).order_by(Device.site_id)
    return list(db.scalars(query))
