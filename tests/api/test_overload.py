"""Overload: past a shard's backlog bound, ingest answers 429 (policy 'reject') or keeps only
each device's newest batch (policy 'latest'), counting what it dropped; it recovers after."""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.main import create_app
from tests.api.test_ingest import batch
from tests.conftest import ADMIN_KEY, floor_doc

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}


@pytest.fixture(params=["reject", "latest"])
def overload_client(
    request: pytest.FixtureRequest, database_url: str, tmp_path: Path
) -> Iterator[tuple[TestClient, str, int]]:
    """The app with one worker process, its overload policy, and the worker's pid."""
    settings = Settings(
        database_url=database_url,
        home=tmp_path,
        workers=1,
        admin_key=ADMIN_KEY,
        shard_backlog=3,
        max_inflight_batches=100,
        overload_policy=request.param,
    )
    before = set(multiprocessing.active_children())
    with TestClient(create_app(settings)) as client:
        (worker,) = (p.pid for p in multiprocessing.active_children() if p not in before)
        yield client, request.param, worker


def _metric(client: TestClient, name: str) -> float:
    total = 0.0
    for line in client.get("/metrics").text.splitlines():
        if line.startswith(name) and not line.startswith("#"):
            total += float(line.rsplit(" ", 1)[1])
    return total


def test_backlog_bound_holds_and_recovers(
    overload_client: tuple[TestClient, str, int],
) -> None:
    client, policy, worker = overload_client
    site = f"ov-{uuid.uuid4().hex[:6]}"
    device = f"{site}-dev"
    client.put(f"/v1/sites/{site}", json={"name": site}, headers=ADMIN)
    client.put(f"/v1/sites/{site}/floors/G", json=floor_doc(), headers=ADMIN)
    os.kill(worker, signal.SIGSTOP)  # the worker stalls: its backlog can only grow
    try:
        statuses = [
            client.post(
                "/v1/ingest",
                json=batch(site, device, t0=1_700_000_000_000 + 10_000 * k),
                headers=ADMIN,
            ).status_code
            for k in range(10)
        ]
    finally:
        os.kill(worker, signal.SIGCONT)
    assert statuses[:3] == [202, 202, 202]
    if policy == "reject":
        assert statuses[3:] == [429] * 7
        assert _metric(client, 'locus_ingest_rejected_requests_total{reason="shard_backlog"}') == 7
    else:
        assert statuses[3:] == [202] * 7
        # 6 parked batches were replaced by the next one: 6 × 9 samples dropped
        assert _metric(client, 'locus_dropped_samples_total{reason="superseded"}') == 54
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        latest = client.get(f"/v1/devices/{device}/position", headers=ADMIN)
        expected = 1_700_000_000_000 + 10_000 * (2 if policy == "reject" else 9) + 2000
        if latest.status_code == 200 and latest.json()["t"] == expected:
            break
        time.sleep(0.1)
    assert latest.json()["t"] == expected
    # recovered: a new batch goes through at once
    r = client.post(
        "/v1/ingest?wait=true", json=batch(site, device, t0=1_700_001_000_000), headers=ADMIN
    )
    assert r.status_code == 200 and len(r.json()["positions"]) == 3, [
        p["t"] for p in r.json()["positions"]
    ]
