"""Storage outages mid-stream against a real ``locus serve``: PostgreSQL stopped and started
again, and Redis under the Redis topology. While the store is away ingest answers 503 with
``Retry-After``; every batch answered 2xx ends up stored; the service resumes by itself."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.conftest import (
    ADMIN_KEY,
    POSTGRES_ENV,
    LiveServer,
    _drop_postgres,
    _fresh_postgres,
    floor_doc,
    migrated,
)
from tests.e2e.recording import batches, walk
from tests.e2e.servers import OwnPostgres, OwnRedis, postgres_available, redis_available

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
WALK_S = 60
OUTAGE_S = 4.0
ENV = {"LOCUS_INGEST_WAIT_TIMEOUT_S": "15"}


@dataclass
class Traffic:
    """What the devices sent and were answered, and when."""

    acknowledged: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    refused: list[tuple[float, int, str | None, str]] = field(default_factory=list)
    accepted_at: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)


def _stream(url: str, devices: list[str], traffic: Traffic) -> list[threading.Thread]:
    """Start one thread per device posting its walk, a batch each 0.1 s, half of them with
    ``?wait=true``; a batch refused with 503 or 429 is sent again after (at most 1 s of) its
    Retry-After, as a client keeping its data would."""

    def run(k: int, device: str) -> None:
        http = httpx.Client(base_url=url, headers=ADMIN, timeout=60)
        path = "/v1/ingest?wait=true" if k % 2 else "/v1/ingest"
        for body in batches(walk(WALK_S, seed=k), 3, site="outage", device=device):
            while True:
                try:
                    r = http.post(path, json=body)
                except httpx.HTTPError as exc:
                    traffic.failures.append(f"{device}: {exc!r}")
                    return
                if r.is_success:
                    traffic.accepted_at.append(time.monotonic())
                    traffic.acknowledged[device] += r.json().get("positions", [])
                    break
                if r.status_code not in (429, 503):
                    traffic.failures.append(f"{device}: {r.status_code} {r.text}")
                    return
                retry = r.headers.get("Retry-After")
                traffic.refused.append((time.monotonic(), r.status_code, retry, r.text))
                time.sleep(min(float(retry or 1), 1.0))
            time.sleep(0.1)

    threads = []
    for k, device in enumerate(devices):
        traffic.acknowledged[device] = []
        threads.append(threading.Thread(target=run, args=(k, device), daemon=True))
        threads[-1].start()
    return threads


def _through_outage(
    server: LiveServer, stop: Callable[[], None], start: Callable[[], None]
) -> tuple[Traffic, float]:
    """Stream four devices, stop the store 2 s in and start it again ``OUTAGE_S`` later.

    Returns the traffic and the seconds from the store's return to the first batch accepted
    after it.
    """
    http = httpx.Client(base_url=server.url, headers=ADMIN, timeout=60)
    assert http.put("/v1/sites/outage", json={"name": "o"}).status_code == 201
    assert http.put("/v1/sites/outage/floors/G", json=floor_doc(pathloss=True)).is_success
    traffic = Traffic()
    devices = [f"dev-{k}" for k in range(4)]
    threads = _stream(server.url, devices, traffic)
    time.sleep(2)
    stop()
    time.sleep(OUTAGE_S)
    start()
    back = time.monotonic()
    for thread in threads:
        thread.join(timeout=240)
    assert not any(t.is_alive() for t in threads), "the devices did not finish their walks"
    assert not traffic.failures, traffic.failures
    recovered = min(t for t in traffic.accepted_at if t > back) - back

    refused = [r for r in traffic.refused if r[1] == 503]
    assert refused, "no request met the outage"
    assert all(retry is not None and int(retry) >= 1 for _, _, retry, _ in refused), refused
    # every acknowledged batch was stored: each position answered is in the history, and
    # the history has a position for each second of every walk (refused batches were resent)
    time.sleep(3)
    for device in devices:
        stored = http.get(
            f"/v1/sites/outage/devices/{device}/positions", params={"limit": 10000}
        ).json()["items"]
        ts = [p["t"] for p in stored]
        assert {p["t"] for p in traffic.acknowledged[device]} <= set(ts), device
        assert ts == sorted(ts) and len(ts) == len(set(ts)), device
        assert len(ts) >= WALK_S - 2 and ts[-1] >= walk(WALK_S)[-1]["t"] - 2000, (device, len(ts))
        assert max(b - a for a, b in zip(ts, ts[1:], strict=False)) <= 5000, device
    return traffic, recovered


@pytest.fixture
def own_postgres() -> Iterator[OwnPostgres]:
    """A PostgreSQL server of this test's own, started."""
    if not postgres_available():
        pytest.skip("PostgreSQL server binaries not installed")
    server = OwnPostgres()
    server.start()
    yield server
    server.remove()


@pytest.mark.postgres
def test_a_postgres_outage_answers_503_loses_no_acknowledged_batch_and_heals(
    own_postgres: OwnPostgres, tmp_path: Path
) -> None:
    url = migrated(own_postgres.url)
    server = LiveServer(database_url=url, home=tmp_path, workers=2, env=ENV)
    try:
        traffic, recovered = _through_outage(server, own_postgres.stop, own_postgres.start)
    finally:
        server.stop()
    messages = {text for _, status, _, text in traffic.refused if status == 503}
    assert any("database is unavailable" in m for m in messages), messages
    assert recovered < 10, recovered
    print(f"postgres outage: {len(traffic.refused)} refusals, ingest back {recovered:.1f} s after")


@pytest.mark.redis
def test_a_redis_outage_answers_503_loses_no_acknowledged_batch_and_heals(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    if not redis_available():
        pytest.skip("redis-server not installed")
    base = _postgres_base()
    own_redis = OwnRedis()
    own_redis.start()
    database_url, name = _fresh_postgres(base)
    migrated(database_url)
    server = None
    try:
        server = LiveServer(
            database_url=database_url,
            home=tmp_path,
            workers=2,
            env=ENV | {"LOCUS_LEASE_S": "2"},
            extra_args=["--broker", own_redis.url],
        )
        traffic, recovered = _through_outage(server, own_redis.stop, own_redis.start)
    finally:
        if server is not None:
            server.stop()
        own_redis.remove()
        _drop_postgres(base, name)
    messages = {text for _, status, _, text in traffic.refused if status == 503}
    assert any("Redis is unavailable" in m for m in messages), messages
    assert recovered < 10, recovered
    print(f"redis outage: {len(traffic.refused)} refusals, ingest back {recovered:.1f} s after")


def _postgres_base() -> str:
    """Return the PostgreSQL server the Redis topology stores positions in (skip without)."""
    import os

    from sqlalchemy import create_engine

    base = os.environ.get(POSTGRES_ENV, "postgresql+psycopg://postgres@127.0.0.1:5432/postgres")
    try:
        create_engine(base).connect().close()
    except Exception:
        pytest.skip("the Redis topology needs PostgreSQL (LOCUS_TEST_POSTGRES_URL)")
    return base
