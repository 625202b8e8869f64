"""Readiness tells a load balancer the truth: a node is ready only when its database answers
and workers will process the ingest it accepts."""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

from fastapi.testclient import TestClient

from app.core.config import Settings
from app.main import create_app
from tests.conftest import ADMIN_KEY

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}


def test_a_node_with_workers_is_ready(client: TestClient) -> None:
    r = client.get("/readyz")
    assert r.status_code == 200
    assert r.json() == {"status": "ready", "database": True, "workers": True}


def test_an_embedded_broker_without_workers_is_not_ready(database_url: str, tmp_path: Path) -> None:
    settings = Settings(
        database_url=database_url, home=tmp_path, workers=0, broker="memory", admin_key=ADMIN_KEY
    )
    with TestClient(create_app(settings)) as client:
        r = client.get("/readyz")
        assert r.status_code == 503
        error = r.json()["error"]
        assert error["code"] == "unavailable" and error["message"] == "not ready"
        (detail,) = error["details"]
        assert detail["database"] is True and detail["workers"] is False
        assert any("no filter workers" in reason for reason in detail["reasons"])
        # what it would have accepted is refused, not lost
        sample = {"t": 1_700_000_000_000, "id": "aa:00:00:00:00:01", "rssi": -50}
        body = {"device_id": "d", "site_id": "s", "wifi": [sample]}
        r = client.post("/v1/ingest", json=body, headers=ADMIN)
        assert r.status_code == 503 and r.json()["error"]["code"] == "unavailable"


def test_healthz_reports_the_installed_package_version(client: TestClient) -> None:
    r = client.get("/healthz")
    assert r.status_code == 200
    assert r.json()["version"] == importlib.metadata.version("locus")
    assert client.get("/openapi.json").json()["info"]["version"] == r.json()["version"]
