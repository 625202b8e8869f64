"""The upgrade that stores a device's position at a time once keeps the first of the repeats
an earlier schema let in, and from then on the database refuses a repeat (run on SQLite and,
in the PostgreSQL run, on PostgreSQL)."""

from __future__ import annotations

from typing import Any

import pytest
import sqlalchemy as sa
from alembic import command

from app.core.db import make_engine, upgrade_database
from tests.api.test_migration_devices_by_site import T0, _alembic, _position


def _positions(engine: sa.Engine) -> sa.Table:
    meta = sa.MetaData()
    meta.reflect(engine, only=["positions"])
    return meta.tables["positions"]


def test_the_upgrade_keeps_one_of_each_repeated_position(new_database: Any) -> None:
    url = new_database()
    command.upgrade(_alembic(url), "0008")
    engine = make_engine(url)
    positions = _positions(engine)
    with engine.begin() as db:
        db.execute(
            positions.insert(),
            [
                _position("s", "tag", T0),
                _position("s", "tag", T0),  # stored by two workers
                _position("s", "tag", T0, smoothed=True),  # the refined one beside it
                _position("s", "other", T0),
                _position("s", "tag", T0 + 1000),
            ],
        )
        first = db.scalar(sa.select(sa.func.min(positions.c.id)))
    engine.dispose()

    upgrade_database(url)

    engine = make_engine(url)
    with engine.connect() as db:
        kept = db.execute(
            sa.select(
                positions.c.id, positions.c.device_id, positions.c.t, positions.c.smoothed
            ).order_by(positions.c.id)
        ).all()
        assert [tuple(r)[1:] for r in kept] == [
            ("tag", T0, False),
            ("tag", T0, True),
            ("other", T0, False),
            ("tag", T0 + 1000, False),
        ]
        assert kept[0].id == first
    with pytest.raises(sa.exc.IntegrityError), engine.begin() as db:
        db.execute(positions.insert(), [_position("s", "tag", T0 + 1000)])
    engine.dispose()

    command.downgrade(_alembic(url), "0008")
    engine = make_engine(url)
    with engine.begin() as db:
        db.execute(positions.insert(), [_position("s", "tag", T0 + 1000)])
        assert db.scalar(sa.select(sa.func.count()).select_from(positions)) == 5
    engine.dispose()
