"""Fixtures shared by the suite: a real database (SQLite, or PostgreSQL when configured),
the real app with real worker processes, and a real ``locus serve`` subprocess."""

from __future__ import annotations

import copy
import os
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text

from app.core.config import Settings
from app.core.db import make_engine, make_sessionmaker, upgrade_database
from app.keys.bootstrap import bootstrap_admin
from app.main import create_app

ADMIN_KEY = "lk_t3st-Adm1n-k3y-f0r-the-su1te-Q7x"
POSTGRES_ENV = "LOCUS_TEST_POSTGRES_URL"

FLOOR_DOC: dict[str, Any] = {
    "type": "FeatureCollection",
    "properties": {"level": 0, "height": 4.0, "name": "Ground"},
    "features": [
        {
            "type": "Feature",
            "properties": {"kind": "outline"},
            "geometry": {
                "type": "Polygon",
                "coordinates": [[[0, 0], [20, 0], [20, 10], [0, 10], [0, 0]]],
            },
        },
        {
            "type": "Feature",
            "properties": {"kind": "wall"},
            "geometry": {"type": "LineString", "coordinates": [[10, 0], [10, 7]]},
        },
        {
            "type": "Feature",
            "properties": {"kind": "zone", "name": "Lab"},
            "geometry": {
                "type": "Polygon",
                "coordinates": [[[12, 2], [16, 2], [16, 6], [12, 6], [12, 2]]],
            },
        },
        {
            "type": "Feature",
            "properties": {
                "kind": "transmitter",
                "id": "aa:00:00:00:00:01",
                "tech": "wifi",
                "A": -40,
                "B": 10,
                "sigma": 4,
            },
            "geometry": {"type": "Point", "coordinates": [1, 1]},
        },
        {
            "type": "Feature",
            "properties": {
                "kind": "transmitter",
                "id": "aa:00:00:00:00:02",
                "tech": "wifi",
                "A": -40,
                "B": 10,
                "sigma": 4,
            },
            "geometry": {"type": "Point", "coordinates": [19, 1]},
        },
        {
            "type": "Feature",
            "properties": {
                "kind": "transmitter",
                "id": "aa:00:00:00:00:03",
                "tech": "wifi",
                "A": -40,
                "B": 10,
                "sigma": 4,
            },
            "geometry": {"type": "Point", "coordinates": [10, 9]},
        },
    ],
}


def floor_doc(*, pathloss: bool = False) -> dict[str, Any]:
    """Return a fresh copy of the small test floor: 20 × 10 m, a wall, a zone, 3 APs.

    Without ``pathloss`` the APs have positions only (an uncalibrated site, positioned by
    the weighted centroid, one estimate per scan); with it they carry A, B and sigma and
    devices get the particle filter.
    """
    doc = copy.deepcopy(FLOOR_DOC)
    if not pathloss:
        for feature in doc["features"]:
            for key in ("A", "B", "sigma"):
                feature["properties"].pop(key, None)
    return doc


def _fresh_postgres(base_url: str) -> tuple[str, str]:
    name = f"locus_test_{uuid.uuid4().hex[:10]}"
    admin = create_engine(base_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    admin.dispose()
    return base_url.rsplit("/", 1)[0] + "/" + name, name


def _drop_postgres(base_url: str, name: str) -> None:
    admin = create_engine(base_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    admin.dispose()


@pytest.fixture(scope="session")
def new_database(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """Return a factory of empty databases: SQLite files, or PostgreSQL databases."""
    base = os.environ.get(POSTGRES_ENV)
    created: list[str] = []

    def make() -> str:
        if base:
            url, name = _fresh_postgres(base)
            created.append(name)
            return url
        folder = tmp_path_factory.mktemp("db")
        return f"sqlite:///{folder / 'locus.db'}"

    yield make
    for name in created:
        _drop_postgres(base, name)  # type: ignore[arg-type]


def migrated(url: str) -> str:
    """Upgrade the database at ``url`` and store the test admin key."""
    upgrade_database(url)
    engine = make_engine(url)
    bootstrap_admin(sessions=make_sessionmaker(engine), settings=Settings(admin_key=ADMIN_KEY))
    engine.dispose()
    return url


@pytest.fixture(scope="session")
def database_url(new_database: Any) -> str:
    """A migrated database shared by the session's API tests (tests use unique site ids)."""
    return migrated(new_database())


@pytest.fixture(scope="session")
def settings(database_url: str, tmp_path_factory: pytest.TempPathFactory) -> Settings:
    """Settings of the in-process app: one worker process, the shared test database."""
    return Settings(
        database_url=database_url,
        home=tmp_path_factory.mktemp("home"),
        workers=1,
        admin_key=ADMIN_KEY,
        flush_after_s=0.2,
    )


@pytest.fixture(scope="session")
def client(settings: Settings) -> Iterator[TestClient]:
    """The real app (real worker process, real database) behind Starlette's test client."""
    with TestClient(create_app(settings)) as test_client:
        yield test_client


@pytest.fixture
def admin() -> dict[str, str]:
    """Headers of the bootstrap admin key."""
    return {"Authorization": f"Bearer {ADMIN_KEY}"}


@pytest.fixture
def site_id(client: TestClient, admin: dict[str, str]) -> str:
    """A new site with the small test floor 'G'."""
    sid = f"s-{uuid.uuid4().hex[:8]}"
    assert client.put(f"/v1/sites/{sid}", json={"name": sid}, headers=admin).status_code == 201
    r = client.put(f"/v1/sites/{sid}/floors/G", json=floor_doc(), headers=admin)
    assert r.status_code == 201, r.text
    return sid


def make_key(
    client: TestClient, admin: dict[str, str], role: str, site: str | None
) -> dict[str, str]:
    """Create a key and return its Authorization header."""
    body: dict[str, Any] = {"role": role}
    if site is not None:
        body["site_id"] = site
    r = client.post("/v1/keys", json=body, headers=admin)
    assert r.status_code == 201, r.text
    return {"Authorization": f"Bearer {r.json()['key']}"}


def free_port() -> int:
    """Return a free TCP port on loopback."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LiveServer:
    """A real ``locus serve`` subprocess on loopback."""

    def __init__(
        self,
        *,
        database_url: str,
        home: Path,
        workers: int,
        env: dict[str, str] | None = None,
        extra_args: list[str] | None = None,
    ):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = home / "serve.log"
        environ = (
            os.environ | {"LOCUS_ADMIN_KEY": ADMIN_KEY, "LOCUS_FLUSH_AFTER_S": "0.2"} | (env or {})
        )
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "app.cli",
                "serve",
                "--port",
                str(self.port),
                "--database-url",
                database_url,
                "--workers",
                str(workers),
                "--home",
                str(home),
                *(extra_args or []),
            ],
            stdout=self.log.open("w"),
            stderr=subprocess.STDOUT,
            env=environ,
        )
        self.wait_ready()

    def wait_ready(self, timeout: float = 90.0) -> None:
        """Block until /readyz answers 200."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited: {self.log.read_text()[-3000:]}")
            try:
                if httpx.get(self.url + "/readyz", timeout=1).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"server not ready: {self.log.read_text()[-3000:]}")

    def stop(self) -> None:
        """Stop the server (SIGTERM, then SIGKILL)."""
        self.process.terminate()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


@pytest.fixture
def live_server(new_database: Any, tmp_path: Path) -> Iterator[LiveServer]:
    """A real server with 2 worker processes on a fresh database."""
    server = LiveServer(database_url=new_database(), home=tmp_path, workers=2)
    yield server
    server.stop()
