"""The upgrade to devices keyed by (site, device) keeps everything the previous schema
stored: every position, every snapshot, every key, each under its own site (run on SQLite
and, in the PostgreSQL run, on PostgreSQL)."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from alembic import command
from alembic.config import Config
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.core.db import make_engine, upgrade_database
from app.core.security import hash_key
from app.main import create_app
from tests.conftest import ADMIN_KEY

MIGRATIONS = Path(__file__).resolve().parents[2] / "migrations"
T0 = 1_700_000_000_000
SNAPSHOT = b"\x93NUMPY-not-parsed-by-the-migration\x00\xff"
WRITTEN = datetime(2026, 11, 30, 12, 0, tzinfo=UTC)


def _alembic(url: str) -> Config:
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return config


def _position(site: str, device: str, t: int, smoothed: bool = False) -> dict[str, Any]:
    return {
        "site_id": site,
        "device_id": device,
        "floor_id": "G",
        "t": t,
        "x": 1.0 + (t - T0) / 1000,
        "y": 2.0,
        "z": 0.0,
        "heading": None,
        "accuracy": 1.5,
        "speed": None,
        "method": "pf",
        "computed_at": T0 + 10_000,
        "smoothed": smoothed,
    }


def _write_previous_schema(url: str) -> None:
    """Store rows as revision 0005 did: device_states keyed by device id alone."""
    engine = make_engine(url)
    meta = sa.MetaData()
    meta.reflect(engine, only=["sites", "api_keys", "positions", "device_states"])
    sites, keys, positions, states = (
        meta.tables[n] for n in ("sites", "api_keys", "positions", "device_states")
    )
    with engine.begin() as db:
        for site in ("old-a", "old-b"):
            db.execute(
                sites.insert().values(
                    id=site,
                    name=site,
                    engine="pf",
                    map_version=1,
                    created_at=WRITTEN,
                    updated_at=WRITTEN,
                )
            )
        db.execute(
            keys.insert().values(
                key_hash=hash_key(ADMIN_KEY), role="admin", label="bootstrap", created_at=WRITTEN
            )
        )
        rows = [_position("old-a", "tag-1", T0 + 1000 * k) for k in range(3)]
        rows += [_position("old-a", "tag-1", T0, smoothed=True)]
        rows += [_position("old-b", "tag-2", T0 + 500)]
        db.execute(positions.insert(), rows)
        db.execute(
            states.insert().values(
                device_id="tag-1",
                site_id="old-a",
                t=T0 + 2000,
                snapshot=SNAPSHOT,
                updated_at=WRITTEN,
            )
        )
    engine.dispose()


def test_the_upgrade_keeps_every_row_under_its_site(new_database: Any, tmp_path: Path) -> None:
    url = new_database()
    command.upgrade(_alembic(url), "0005")
    _write_previous_schema(url)

    upgrade_database(url)

    engine = make_engine(url)
    with engine.connect() as db:
        states = db.execute(sa.text("SELECT site_id, device_id, t, snapshot FROM device_states"))
        assert [tuple(r) for r in states] == [("old-a", "tag-1", T0 + 2000, SNAPSHOT)]
        devices = db.execute(
            sa.text("SELECT site_id, device_id, last_t, last_seen FROM devices ORDER BY site_id")
        )
        assert [tuple(r) for r in devices] == [
            ("old-a", "tag-1", T0 + 2000, int(WRITTEN.timestamp() * 1000)),
            ("old-b", "tag-2", T0 + 500, T0 + 10_000),
        ]
        assert db.scalar(sa.text("SELECT count(*) FROM positions")) == 5
    engine.dispose()

    settings = Settings(database_url=url, home=tmp_path, workers=0)
    admin = {"Authorization": f"Bearer {ADMIN_KEY}"}
    with TestClient(create_app(settings)) as client:
        listed = client.get("/v1/sites/old-a/devices", headers=admin).json()["items"]
        assert [(d["device_id"], d["position"]["t"]) for d in listed] == [("tag-1", T0 + 2000)]
        history = client.get("/v1/sites/old-a/devices/tag-1/positions", headers=admin).json()
        assert [(p["t"], p["smoothed"]) for p in history["items"]] == [
            (T0, True),
            (T0 + 1000, False),
            (T0 + 2000, False),
        ]
        other = client.get("/v1/devices/tag-2/position", headers=admin).json()
        assert other["site_id"] == "old-b" and other["t"] == T0 + 500

    # and back: the previous schema gets its rows again
    command.downgrade(_alembic(url), "0005")
    engine = make_engine(url)
    with engine.connect() as db:
        assert db.scalar(sa.text("SELECT count(*) FROM positions")) == 5
        assert db.scalar(sa.text("SELECT count(*) FROM device_states")) == 1
        assert db.scalar(sa.text("SELECT count(*) FROM api_keys")) == 1
    engine.dispose()
