"""Jobs survive restarts: a radio-map build or track fit whose process stopped ends failed,
saying so, while a job that a live process (this one or a neighbour) renews is left alone."""

from __future__ import annotations

import time
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.db import make_engine, make_sessionmaker, session_scope
from app.core.jobs import tend_jobs
from app.core.time import utcnow
from app.main import create_app
from app.radiomaps.models import RadioMapJob
from app.sites.models import Site
from app.tracks.models import Track
from tests.api.test_tracks import _track
from tests.conftest import ADMIN_KEY, floor_doc, migrated

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
SITE = "restarts"


def _settings(url: str, home: Path, **changes: Any) -> Settings:
    return Settings(database_url=url, home=home, workers=0, admin_key=ADMIN_KEY, **changes)


def _store_jobs(sessions: sessionmaker[Session], jobs: dict[str, tuple[str, datetime]]) -> None:
    """Store the site and, for each name, a build job and a track fit in that status, last
    renewed at that time."""
    with session_scope(sessions) as db:
        if db.get(Site, SITE) is None:
            db.add(Site(id=SITE, name=SITE))
            db.flush()
        for name, (status, renewed) in jobs.items():
            db.add(
                RadioMapJob(
                    id=f"build-{name}",
                    site_id=SITE,
                    status=status,
                    progress=0.4,
                    created_at=renewed,
                    updated_at=renewed,
                )
            )
            db.add(
                Track(
                    id=f"track-{name}",
                    site_id=SITE,
                    floor_id="G",
                    device_id="saver",
                    status=status,
                    request={},
                    created_at=renewed,
                    updated_at=renewed,
                )
            )


def _statuses(client: TestClient, name: str) -> list[tuple[str, str | None]]:
    build = client.get(f"/v1/sites/{SITE}/radiomap/build/build-{name}", headers=ADMIN).json()
    track = client.get(f"/v1/tracks/track-{name}", headers=ADMIN).json()
    return [(build["status"], build["error"]), (track["status"], track["error"])]


def test_jobs_of_a_stopped_process_are_failed_at_start(new_database: Any, tmp_path: Path) -> None:
    url = migrated(new_database())
    engine = make_engine(url)
    before_restart = utcnow() - timedelta(minutes=5)
    _store_jobs(
        make_sessionmaker(engine),
        {
            "running": ("running", before_restart),
            "queued": ("queued", before_restart),
            "done": ("done", before_restart),
            # a neighbour API process on the same database renewed this one a moment ago
            "neighbour": ("running", utcnow()),
        },
    )
    engine.dispose()
    with TestClient(create_app(_settings(url, tmp_path))) as client:
        for name in ("running", "queued"):
            for status, error in _statuses(client, name):
                assert status == "failed"
                assert error is not None
                assert error.startswith("interrupted by a server restart or crash")
                assert error.endswith("submit it again")
        assert _statuses(client, "done") == [("done", None), ("done", None)]
        assert _statuses(client, "neighbour") == [("running", None), ("running", None)]


def test_a_job_nobody_renews_fails_within_a_lease(new_database: Any, tmp_path: Path) -> None:
    url = migrated(new_database())
    lease_s = 0.2
    with TestClient(create_app(_settings(url, tmp_path, job_lease_s=lease_s))) as client:
        _store_jobs(client.app.state.locus.sessions, {"gone": ("running", utcnow())})
        client.put(f"/v1/sites/{SITE}/floors/G", json=floor_doc(), headers=ADMIN)
        # this process's own fit is renewed while the pool starts and fits it
        r = client.post("/v1/tracks", json=_track(SITE), headers=ADMIN)
        assert r.status_code == 202, r.text
        own = r.json()["track_id"]
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            fit = client.get(f"/v1/tracks/{own}", headers=ADMIN).json()
            if fit["status"] in ("done", "failed") and _statuses(client, "gone")[0][0] != "running":
                break
            time.sleep(0.1)
        assert fit["status"] == "done", fit
        assert [status for status, _ in _statuses(client, "gone")] == ["failed", "failed"]


def test_a_process_renews_its_own_jobs_however_old(new_database: Any) -> None:
    engine = make_engine(migrated(new_database()))
    sessions = make_sessionmaker(engine)
    long_ago = utcnow() - timedelta(hours=1)
    _store_jobs(sessions, {"mine": ("running", long_ago), "orphan": ("running", long_ago)})
    now = utcnow()
    with session_scope(sessions) as db:
        failed = tend_jobs(db, Track, alive=["track-mine"], now=now, lease_s=30.0)
    assert failed == 1
    with session_scope(sessions) as db:
        mine, orphan = db.get(Track, "track-mine"), db.get(Track, "track-orphan")
        assert mine is not None and orphan is not None
        assert (mine.status, mine.updated_at, mine.error) == ("running", now, None)
        assert orphan.status == "failed" and orphan.error is not None
        assert now.strftime("%Y-%m-%dT%H:%M:%SZ") in orphan.error
    engine.dispose()
