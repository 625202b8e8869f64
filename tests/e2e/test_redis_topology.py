"""Two API nodes and three worker nodes on the local Redis and PostgreSQL: a worker killed
with SIGKILL mid-stream loses no acknowledged batch; its devices continue on the others."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
import redis
from sqlalchemy import create_engine

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

REDIS_URL = os.environ.get("LOCUS_TEST_REDIS_URL", "redis://127.0.0.1:6379/14")
PG_URL = os.environ.get(POSTGRES_ENV, "postgresql+psycopg://postgres@127.0.0.1:5432/postgres")


def _reachable() -> bool:
    try:
        redis.Redis.from_url(REDIS_URL).ping()
        create_engine(PG_URL).connect().close()
    except Exception:
        return False
    return True


pytestmark = [
    pytest.mark.redis,
    pytest.mark.skipif(not _reachable(), reason="needs local Redis and PostgreSQL"),
]


def _worker(database_url: str, home: Path, index: int) -> subprocess.Popen[bytes]:
    env = os.environ | {"LOCUS_LEASE_S": "2"}
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "app.cli",
            "worker",
            "--broker",
            REDIS_URL,
            "--database-url",
            database_url,
            "--home",
            str(home),
        ],
        stdout=(home / f"worker{index}.log").open("w"),
        stderr=subprocess.STDOUT,
        env=env,
    )


def test_killed_worker_node_loses_nothing(tmp_path: Path, monkeypatch: Any) -> None:
    monkeypatch.setenv(POSTGRES_ENV, PG_URL)
    redis.Redis.from_url(REDIS_URL).flushdb()
    database_url, name = _fresh_postgres(PG_URL)
    migrated(database_url)
    workers = [_worker(database_url, tmp_path, i) for i in range(3)]
    apis = []
    try:
        for i in range(2):
            home = tmp_path / f"api{i}"
            home.mkdir()
            apis.append(
                LiveServer(
                    database_url=database_url,
                    home=home,
                    workers=0,
                    extra_args=["--broker", REDIS_URL],
                )
            )
        admin = {"Authorization": f"Bearer {ADMIN_KEY}"}
        http = [httpx.Client(base_url=a.url, headers=admin, timeout=90) for a in apis]
        assert http[0].put("/v1/sites/multi", json={"name": "m"}).status_code == 201
        assert (
            http[0].put("/v1/sites/multi/floors/G", json=floor_doc(pathloss=True)).status_code
            == 201
        )
        time.sleep(2.5)  # site version cache on the other API node
        devices = [f"multi-{k}" for k in range(6)]
        streams = {
            d: batches(walk(45, seed=k), 3, site="multi", device=d) for k, d in enumerate(devices)
        }
        acknowledged: dict[str, list[dict]] = {d: [] for d in devices}
        failures: list[str] = []

        def run(k: int, device: str) -> None:
            for step, body in enumerate(streams[device]):
                r = http[(k + step) % 2].post("/v1/ingest?wait=true", json=body)
                if r.status_code != 200:
                    failures.append(f"{device} step {step}: {r.status_code} {r.text}")
                    return
                acknowledged[device] += r.json()["positions"]
                time.sleep(0.1)

        threads = [threading.Thread(target=run, args=(k, d)) for k, d in enumerate(devices)]
        for thread in threads:
            thread.start()
        time.sleep(1.5)
        victim = (tmp_path / "worker0.log").read_text().split(" started")[0].rsplit(" ", 1)[1]
        leases = redis.Redis.from_url(REDIS_URL)
        taken = {s for s in range(16) if leases.get(f"locus:lease:{s}") == victim.encode()}
        assert taken, "the worker to kill owned no shard"
        seen = [len((tmp_path / f"worker{i}.log").read_text()) for i in (1, 2)]
        workers[0].send_signal(signal.SIGKILL)
        killed_at = time.monotonic()
        for thread in threads:
            thread.join(timeout=120)
        assert not failures, failures
        # what the survivors logged after the kill
        survivors = "".join(
            (tmp_path / f"worker{i}.log").read_text()[offset:]
            for i, offset in zip((1, 2), seen, strict=True)
        )
        assert all(f"took shard {shard} " in survivors for shard in taken)
        assert time.monotonic() - killed_at < 60
        for device in devices:
            stored = http[1].get(f"/v1/devices/{device}/positions?limit=10000").json()["items"]
            ts = [p["t"] for p in stored]
            assert {p["t"] for p in acknowledged[device]} <= set(ts)
            assert ts == sorted(ts) and len(ts) == len(set(ts)), device
            # one position per 1 s window of the 45 s walk, through the kill: the entries
            # whose samples the dead worker held were replayed on its devices' snapshots
            assert ts[-1] >= walk(45)[-1]["t"] - 2000, (device, len(ts))
            assert {b - a for a, b in zip(ts, ts[1:], strict=False)} == {1000}, (device, ts)
    finally:
        for api in apis:
            api.stop()
        for w in workers:
            if w.poll() is None:
                w.terminate()
        for w in workers:
            w.wait(timeout=30)
        _drop_postgres(PG_URL, name)
