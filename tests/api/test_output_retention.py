"""The retention bound: a message its output could not deliver for ``output_retention_s``
is given up, counted failed on the output's status and in /metrics, and delivery goes on
with what is newer. An app of its own, with a bound of seconds."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.main import create_app
from tests.api.test_outputs import T0, after_refresh, status_of, stored_positions, walk
from tests.conftest import ADMIN_KEY, floor_doc, migrated
from tests.receivers import SECRET, Receiver, until

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
RETENTION_S = 3.0


@pytest.fixture
def short_retention(new_database: Any, tmp_path: Path) -> Iterator[tuple[TestClient, Settings]]:
    settings = Settings(
        database_url=migrated(new_database()),
        home=tmp_path,
        workers=1,
        admin_key=ADMIN_KEY,
        flush_after_s=0.2,
        output_retention_s=RETENTION_S,
        output_retry_base_s=0.2,
        output_retry_max_s=0.5,
    )
    with TestClient(create_app(settings)) as client:
        yield client, settings


def metric(client: TestClient, name: str, site_id: str, output_id: str) -> float:
    """Return the output's sample of ``name`` in /metrics (0 when it has none)."""
    text = client.get("/metrics", headers=ADMIN).text
    labels = rf'\{{(?=[^}}]*output_id="{output_id}")(?=[^}}]*site_id="{site_id}")[^}}]*\}}'
    found = re.search(rf"^{name}{labels} (\S+)$", text, flags=re.M)
    return float(found.group(1)) if found else 0.0


def test_undeliverable_messages_are_counted_failed_after_the_retention_bound(
    short_retention: tuple[TestClient, Settings],
) -> None:
    client, settings = short_retention
    site = "retained"
    assert client.put(f"/v1/sites/{site}", json={"name": site}, headers=ADMIN).is_success
    assert client.put(f"/v1/sites/{site}/floors/G", json=floor_doc(), headers=ADMIN).is_success
    receiver = Receiver()
    try:
        receiver.refusing = True
        body = {"kind": "webhook", "url": receiver.url, "secret": SECRET, "events": ["position"]}
        assert client.put(f"/v1/sites/{site}/outputs/hook", json=body, headers=ADMIN).is_success
        after_refresh(settings)
        client.post("/v1/ingest?wait=true", json=walk(site, "lost"), headers=ADMIN)
        lost = len(stored_positions(client, ADMIN, site, "lost"))
        # within the bound: waiting, retried, not failed
        early = status_of(client, ADMIN, site, "hook")
        assert (early["pending"], early["failed"]) == (lost, 0), early
        until(lambda: metric(client, "locus_output_retried_total", site, "hook") > 0)
        status = until(
            lambda: (s := status_of(client, ADMIN, site, "hook"))["failed"] == lost and s,
            RETENTION_S + 20,
            "the messages counted failed",
        )
        assert status["pending"] == 0 and status["delivered"] == 0
        assert "503" in status["last_error"]
        assert metric(client, "locus_output_failed_total", site, "hook") == lost
        assert metric(client, "locus_output_delivered_total", site, "hook") == 0
        until(lambda: metric(client, "locus_output_pending", site, "hook") == 0)

        # the receiver back: what is stored from then on is delivered, the failed stay failed
        receiver.refusing = False
        later = walk(site, "lost", t0=T0 + 60_000)
        client.post("/v1/ingest?wait=true", json=later, headers=ADMIN)
        fresh = len(stored_positions(client, ADMIN, site, "lost")) - lost
        until(lambda: len(receiver.accepted()) == fresh, 30, "the newer messages delivered")
        assert all(m["t"] >= T0 + 60_000 for m in receiver.accepted())
        done = until(lambda: (s := status_of(client, ADMIN, site, "hook"))["delivered"] and s)
        assert (done["delivered"], done["failed"], done["last_error"]) == (fresh, lost, None)
        assert metric(client, "locus_output_delivered_total", site, "hook") == fresh
    finally:
        receiver.close()
