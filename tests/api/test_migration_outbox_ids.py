"""The upgrade that makes outbox ids never reused keeps the waiting messages, and from then
on a message stored after the outbox was emptied gets a new id, not a sent one's (run on
SQLite and, in the PostgreSQL run, on PostgreSQL)."""

from __future__ import annotations

from typing import Any

import sqlalchemy as sa
from alembic import command

from app.core.db import make_engine, upgrade_database
from tests.api.test_migration_devices_by_site import _alembic


def _row(payload: str) -> dict[str, Any]:
    return {
        "site_id": "s",
        "output_id": "hook",
        "device_id": "tag",
        "kind": "position",
        "payload": payload,
        "stored_at": 1,
    }


def test_outbox_ids_survive_the_upgrade_and_are_never_handed_out_again(
    new_database: Any,
) -> None:
    url = new_database()
    command.upgrade(_alembic(url), "0012")
    engine = make_engine(url)
    meta = sa.MetaData()
    meta.reflect(engine, only=["outbox"])
    outbox = meta.tables["outbox"]
    with engine.begin() as db:
        db.execute(outbox.insert(), [_row("a"), _row("b")])
        before = db.execute(sa.select(outbox.c.id, outbox.c.payload).order_by("id")).all()
    engine.dispose()

    upgrade_database(url)

    engine = make_engine(url)
    with engine.begin() as db:
        assert db.execute(sa.select(outbox.c.id, outbox.c.payload).order_by("id")).all() == before
        db.execute(sa.delete(outbox))  # all delivered
        db.execute(outbox.insert(), [_row("c")])
        (fresh,) = db.scalars(sa.select(outbox.c.id)).all()
    engine.dispose()
    assert fresh > max(i for i, _ in before)
