"""The whole pipe against a real `locus serve` with worker processes: map upload, batches,
positions over the WebSocket, history, replay determinism, and a worker killed mid-stream."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx
from websockets.sync.client import connect

from tests.conftest import ADMIN_KEY, LiveServer, floor_doc
from tests.e2e.recording import batches, walk

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
# a device is flushed after this many wall seconds of silence; the tests that count the
# positions of `?wait=true` answers need it longer than any stall of a loaded test machine
# between an answer and the next post, or a flush positions a window outside every answer
PATIENT = {"LOCUS_FLUSH_AFTER_S": "3"}


def _setup(server: LiveServer, site: str) -> httpx.Client:
    http = httpx.Client(base_url=server.url, headers=ADMIN, timeout=30)
    assert http.put(f"/v1/sites/{site}", json={"name": site}).status_code == 201
    assert http.put(f"/v1/sites/{site}/floors/G", json=floor_doc(pathloss=True)).status_code == 201
    return http


def _strip(positions: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in p.items() if k != "computed_at"} for p in positions]


def _worker_pids(server_pid: int) -> list[int]:
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if int(stat[1]) == server_pid and b"spawn_main" in cmdline:
            pids.append(int(entry.name))
    return sorted(pids)


def test_positions_flow_from_ingest_to_websocket_and_history(
    new_database: Any, tmp_path: Path
) -> None:
    live_server = LiveServer(database_url=new_database(), home=tmp_path, workers=2, env=PATIENT)
    try:
        _positions_flow(live_server)
    finally:
        live_server.stop()


def _positions_flow(live_server: LiveServer) -> None:
    http = _setup(live_server, "e2e")
    received: list[dict] = []
    ws_url = live_server.url.replace("http", "ws") + f"/v1/ws/positions?site_id=e2e&key={ADMIN_KEY}"
    with connect(ws_url) as ws:

        def listen() -> None:
            try:
                while len(received) < 20:
                    received.append(json.loads(ws.recv(timeout=20)))
            except TimeoutError:
                pass

        listener = threading.Thread(target=listen)
        listener.start()
        time.sleep(0.3)
        answered = []
        for body in batches(walk(20), 9, site="e2e", device="walker"):
            r = http.post("/v1/ingest?wait=true", json=body)
            assert r.status_code == 200, r.text
            answered += r.json()["positions"]
        listener.join(timeout=30)
    # one position per 1 s window; the last window is positioned once the device goes quiet
    assert len(answered) == 19
    assert len(received) == 20
    assert _strip(received[:19]) == _strip(answered)
    history = http.get("/v1/devices/walker/positions").json()["items"]
    assert _strip(history) == _strip(received)
    assert [p["t"] for p in history] == sorted(p["t"] for p in history)
    latest = http.get("/v1/devices/walker/position").json()
    assert latest["t"] == history[-1]["t"]


def test_replay_gives_identical_positions(new_database: Any, tmp_path: Path) -> None:
    runs = []
    for run, size in enumerate((9, 31)):
        home = tmp_path / f"run{run}"
        home.mkdir()
        server = LiveServer(database_url=new_database(), home=home, workers=2, env=PATIENT)
        try:
            http = _setup(server, "replay")
            out = []
            for body in batches(walk(30), size, site="replay", device="replayer"):
                out += http.post("/v1/ingest?wait=true", json=body).json()["positions"]
            runs.append(_strip(out))
        finally:
            server.stop()
    assert len(runs[0]) == 29
    assert runs[0] == runs[1]
    assert all(p["method"] == "pf" for p in runs[0])


def _cli_replay(server: LiveServer, recording: Path, device: str, speed: float) -> list[dict]:
    out = subprocess.run(
        [sys.executable, "-m", "app.cli", "replay", str(recording), "--server", server.url,
         "--key", ADMIN_KEY, "--device-id", device, "--speed", str(speed)],
        capture_output=True, text=True, check=True, timeout=120,
    )  # fmt: skip
    return [json.loads(line) for line in out.stdout.splitlines()]


def test_replay_command_repeats_positions_and_paces_by_speed(
    new_database: Any, tmp_path: Path
) -> None:
    recording = tmp_path / "walk.json"
    recording.write_text(json.dumps(batches(walk(6), 4, site="cli", device="ignored")))
    runs, elapsed = [], []
    for run, speed in enumerate((2.0, 0.0)):
        home = tmp_path / f"run{run}"
        home.mkdir()
        server = LiveServer(database_url=new_database(), home=home, workers=1)
        try:
            _setup(server, "cli")
            started = time.monotonic()
            printed = _cli_replay(server, recording, "cli-walker", speed)
            runs.append(sorted(_strip(printed), key=lambda p: p["t"]))
            elapsed.append(time.monotonic() - started)
        finally:
            server.stop()
    assert len(runs[0]) >= 5
    assert {p["device_id"] for p in runs[0]} == {"cli-walker"}
    assert runs[0] == runs[1]
    # 5 s of measurement time at twice real time take at least 2.5 s
    assert elapsed[0] >= 2.5


def test_killed_worker_restarts_and_loses_no_acknowledged_batch(live_server: LiveServer) -> None:
    http = _setup(live_server, "crash")
    devices = [f"crash-{k}" for k in range(6)]
    streams = {
        d: batches(walk(40, seed=k), 6, site="crash", device=d) for k, d in enumerate(devices)
    }
    acknowledged: dict[str, list[dict]] = {d: [] for d in devices}
    pids = _worker_pids(live_server.process.pid)
    assert len(pids) == 2
    for step in range(20):
        if step == 8:
            os.kill(pids[0], signal.SIGKILL)
        for d in devices:
            r = http.post("/v1/ingest?wait=true", json=streams[d][step])
            assert r.status_code == 200, r.text
            acknowledged[d] += r.json()["positions"]
    new_pids = _worker_pids(live_server.process.pid)
    assert pids[0] not in new_pids and len(new_pids) == 2
    for d in devices:
        stored = http.get(f"/v1/devices/{d}/positions?limit=10000").json()["items"]
        ts = [p["t"] for p in stored]
        # every acknowledged position is stored, none twice, in time order
        assert {p["t"] for p in acknowledged[d]} <= set(ts)
        assert len(ts) == len(set(ts)) and ts == sorted(ts)
        # and one position a second through the kill: no sample the dead worker held is lost
        assert max(ts) >= walk(40)[-1]["t"] - 1000
        assert {b - a for a, b in zip(ts, ts[1:], strict=False)} == {1000}, (d, ts)
    metrics = http.get("/metrics").text
    assert 'locus_worker_restarts_total{shard="' in metrics
