"""A request awaiting its positions holds its submission, not its parsed batch: a backlog
of such requests would otherwise keep thousands of small objects alive, spread over the
allocator's arenas, which Python does not give back while any object in them lives."""

from __future__ import annotations

import gc
import multiprocessing
import os
import signal
import time
import uuid
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.ingest.schemas import IngestBatch
from app.main import create_app
from tests.api.test_ingest import batch
from tests.conftest import ADMIN_KEY, floor_doc

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
WAITING = 8


@pytest.fixture
def stalled_worker_client(database_url: str, tmp_path: Path) -> Iterator[tuple[TestClient, int]]:
    """The app in this process with one worker process, and the worker's pid."""
    settings = Settings(database_url=database_url, home=tmp_path, workers=1, admin_key=ADMIN_KEY)
    before = set(multiprocessing.active_children())
    with TestClient(create_app(settings)) as client:
        (worker,) = (p.pid for p in multiprocessing.active_children() if p not in before)
        yield client, worker


def _live_batches() -> int:
    gc.collect()
    return sum(1 for o in gc.get_objects() if isinstance(o, IngestBatch))


def test_requests_awaiting_positions_keep_no_parsed_batch(
    stalled_worker_client: tuple[TestClient, int],
) -> None:
    client, worker = stalled_worker_client
    site = f"wait-{uuid.uuid4().hex[:6]}"
    client.put(f"/v1/sites/{site}", json={"name": site}, headers=ADMIN)
    client.put(f"/v1/sites/{site}/floors/G", json=floor_doc(), headers=ADMIN)

    def post(k: int) -> dict:
        body = batch(site, f"{site}-dev{k}")
        r = client.post("/v1/ingest?wait=true", json=body, headers=ADMIN)
        assert r.status_code == 200, r.text
        return r.json()

    with ThreadPoolExecutor(WAITING) as pool:
        os.kill(worker, signal.SIGSTOP)  # the worker stalls: every request must wait
        try:
            answers = [pool.submit(post, k) for k in range(WAITING)]
            runtime = client.app.state.locus.runtime  # type: ignore[attr-defined]
            deadline = time.monotonic() + 10
            while len(runtime.waiting) < WAITING:
                assert time.monotonic() < deadline, "the requests were not all submitted"
                time.sleep(0.02)
            assert _live_batches() == 0
        finally:
            os.kill(worker, signal.SIGCONT)
        results = [a.result(timeout=30) for a in answers]
    assert all(r["accepted"] == 9 and len(r["positions"]) == 3 for r in results), results
