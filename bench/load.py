"""Load benchmark: K devices posting one batch a second to a running `locus serve`.

Drives the server at ``--server`` (with an admin ``--key``) from this separate
process: installs the demo site if it is missing, subscribes to the site's
positions on the WebSocket, then runs K simulated devices (random routes on
the demo floor, BLE scans from the path-loss model) for a fixed time. Every
request uses ``?wait=true``. Prints one row per K: sustained device updates
(positions) per second, p50/p99 of the HTTP answer and of the position's
arrival on the WebSocket (both from the moment the batch was sent), failed
requests, positions the server dropped (WebSocket and ingest drops from
``/metrics``), and with ``--pid`` the server's CPU (API and workers, % of one
core) and RSS.

    locus serve --port 8000 --workers 2 &
    python bench/load.py --server http://127.0.0.1:8000 --key ADMIN_KEY --pid PID \
        --devices 100 1000 5000 --seconds 30

Without ``--server`` it starts its own server per K (embedded SQLite, or
``--broker redis://...``) and stops it afterwards.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
import redis
from websockets.asyncio.client import connect as ws_connect

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app import demo  # noqa: E402

ADMIN = "lk_bench_admin"
"""The admin key of a server this benchmark starts itself."""


def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError):
                continue
            if ppid == pid:
                out.append(int(entry.name))
    return out


def _cpu_seconds(pids: list[int]) -> float:
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / tick
    return total


def _rss_mb(pids: list[int]) -> float:
    total = 0
    for pid in pids:
        try:
            for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
        except OSError:
            continue
    return total / 1024


def _scan(beacons: list[dict], xy: np.ndarray, t: int, rng: random.Random) -> list[dict]:
    out = []
    for b in beacons:
        r = max(0.5, float(np.hypot(*(xy - b["xyz"][:2]))))
        rssi = b["A"] - b["B"] * np.log(r) + rng.gauss(0, b["sigma"])
        if rssi > -95:
            out.append({"t": t, "id": b["id"], "rssi": round(float(rssi), 1)})
    return out


class Connection:
    """A minimal HTTP/1.1 keep-alive client: the load generator must cost far less than the
    server it measures, and a general-purpose client costs about as much per request."""

    def __init__(self, host: str, port: int, key: str) -> None:
        self.host, self.port, self.key = host, port, key
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def post(self, path: str, body: bytes) -> int:
        """Send one POST and return the status code (the body is read and discarded)."""
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        head = (
            f"POST {path} HTTP/1.1\r\nHost: {self.host}\r\nAuthorization: Bearer {self.key}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n"
        )
        self.writer.write(head.encode() + body)
        assert self.reader is not None
        header = await self.reader.readuntil(b"\r\n\r\n")
        status = int(header[9:12])
        length = 0
        for line in header.split(b"\r\n"):
            if line.lower().startswith(b"content-length:"):
                length = int(line.split(b":")[1])
        await self.reader.readexactly(length)
        return status


@dataclass
class Tally:
    """What the devices and the WebSocket saw, each entry stamped with its perf-counter time."""

    http: list[tuple[float, float]] = field(default_factory=list)
    ws: list[tuple[float, float]] = field(default_factory=list)
    errors: list[tuple[float, int]] = field(default_factory=list)
    last_sent: dict[str, float] = field(default_factory=dict)


async def _device(http: Connection, name: str, beacons: list[dict], until: float, tally: Tally,
                  t0: int, wait: bool) -> None:  # fmt: skip
    path = "/v1/ingest?wait=true" if wait else "/v1/ingest"
    rng = random.Random(name)
    walker = demo.Walker(demo.ROUTES[rng.randrange(len(demo.ROUTES))], 1.0 + rng.random() * 0.4)
    await asyncio.sleep(rng.random())
    k = 0
    start = time.monotonic()
    while time.monotonic() < until:
        t = t0 + 1000 * k
        body = {
            "device_id": name,
            "site_id": demo.SITE_ID,
            "ble": _scan(beacons, walker.at(k), t, rng),
        }
        sent = time.perf_counter()
        tally.last_sent[name] = sent
        try:
            status = await http.post(path, json.dumps(body).encode())
        except (OSError, asyncio.IncompleteReadError):
            http.writer = None
            status = 0
        done = time.perf_counter()
        if status in (200, 202):
            tally.http.append((done, done - sent))
        else:
            tally.errors.append((done, status))
        k += 1
        # keep a 1 Hz schedule; a late device does not burst to catch up
        await asyncio.sleep(max(0.0, start + k - time.monotonic()))


async def _watch(url: str, key: str, tally: Tally) -> None:
    """Stamp every position of the site arriving on the WebSocket against its batch's send."""
    ws_url = url.replace("http://", "ws://") + f"/v1/ws/positions?site_id={demo.SITE_ID}&key={key}"
    async with ws_connect(ws_url, max_queue=None) as ws:
        async for raw in ws:
            now = time.perf_counter()
            msg = json.loads(raw)
            sent = tally.last_sent.get(msg.get("device_id", ""))
            if msg.get("type") == "position" and sent is not None:
                tally.ws.append((now, now - sent))


def start_devices(url: str, key: str, devices: int, seconds: float, tally: Tally,
                  prefix: str, wait: bool = True) -> list[asyncio.Task[None]]:  # fmt: skip
    """Start K simulated devices posting at 1 Hz for ``seconds``; return their tasks.

    With ``wait`` each device waits for its positions before its next batch (a closed
    loop); without, batches leave on schedule whatever the server's backlog.
    """
    beacons = [
        {"xyz": f["geometry"]["coordinates"], **f["properties"]}
        for f in demo.load_map()["features"]
        if f["properties"]["kind"] == "transmitter"
    ]
    host, port = url.removeprefix("http://").split(":")
    t0 = int(time.time() * 1000) - 3_600_000
    until = time.monotonic() + seconds
    return [
        asyncio.create_task(
            _device(
                Connection(host, int(port), key), f"{prefix}-{i}", beacons, until, tally, t0, wait
            )
        )
        for i in range(devices)
    ]


async def _run(url: str, key: str, devices: int, seconds: float, warmup: float) -> Tally:
    tally = Tally()
    watcher = asyncio.create_task(_watch(url, key, tally))
    await asyncio.sleep(0.5)
    prefix = f"load-{uuid.uuid4().hex[:6]}"
    await asyncio.gather(*start_devices(url, key, devices, warmup + seconds, tally, prefix))
    await asyncio.sleep(0.5)
    watcher.cancel()
    return tally


def _dropped(url: str, key: str) -> float:
    """Return the server's count of dropped samples and WebSocket messages."""
    text = httpx.get(url + "/metrics", headers={"Authorization": f"Bearer {key}"}).text
    total = 0.0
    for line in text.splitlines():
        if line.startswith(("locus_dropped_samples_total", "locus_ws_dropped_messages_total")):
            total += float(line.rsplit(" ", 1)[1])
    return total


@contextmanager
def _own_server(port: int, workers: int, broker: str) -> Iterator[tuple[str, int]]:
    """Start a server of our own on a fresh home; yield its URL and pid."""
    if broker.startswith("redis"):
        redis.Redis.from_url(broker).flushdb()  # no streams or leases of a past run
    with tempfile.TemporaryDirectory() as home:
        server = subprocess.Popen(
            [sys.executable, "-m", "app.cli", "serve", "--port", str(port), "--workers",
             str(workers), "--home", home, "--broker", broker],
            cwd=ROOT, env=os.environ | {"LOCUS_ADMIN_KEY": ADMIN},
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        url = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                try:
                    if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                        break
                except httpx.HTTPError:
                    time.sleep(0.3)
            yield url, server.pid
        finally:
            server.terminate()
            server.wait(timeout=60)


def measure(url: str, key: str, pid: int | None, devices: int, seconds: float,
            warmup: float) -> dict[str, float]:  # fmt: skip
    """Run K devices against the server at ``url`` and return the row of figures."""
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"}) as http:
        if http.get(f"/v1/sites/{demo.SITE_ID}").status_code == 404:
            demo.install(url, key)
    pids = [] if pid is None else [pid, *_children(pid)]
    dropped0 = _dropped(url, key)
    cpu0, wall0 = _cpu_seconds(pids), time.monotonic()
    tally = asyncio.run(_run(url, key, devices, seconds, warmup))
    cpu = (_cpu_seconds(pids) - cpu0) / (time.monotonic() - wall0) * 100
    measured_from = min(t for t, _ in tally.http) + warmup if tally.http else 0.0
    http_ms = np.array([v for t, v in tally.http if t >= measured_from]) * 1000
    ws_ms = np.array([v for t, v in tally.ws if t >= measured_from]) * 1000

    def pct(a: np.ndarray, q: float) -> float:
        return float(np.percentile(a, q)) if a.size else float("nan")

    return {
        "devices": devices,
        "req/s": http_ms.size / seconds,
        "pos/s": ws_ms.size / seconds,
        "http p50": pct(http_ms, 50),
        "http p99": pct(http_ms, 99),
        "ws p50": pct(ws_ms, 50),
        "ws p99": pct(ws_ms, 99),
        "failed": len(tally.errors),
        "dropped": _dropped(url, key) - dropped0,
        "CPU %": cpu if pids else float("nan"),
        "RSS MB": _rss_mb(pids) if pids else float("nan"),
    }


def main() -> None:
    """Run the benchmark for each device count and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", help="URL of a running server (default: start one per K)")
    parser.add_argument("--key", default=os.environ.get("LOCUS_ADMIN_KEY"), help="admin key")
    parser.add_argument("--pid", type=int, help="the running server's pid, for CPU and RSS")
    parser.add_argument("--devices", type=int, nargs="+", default=[100, 1000, 5000])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--warmup", type=float, default=5.0)
    parser.add_argument("--workers", type=int, default=2, help="own server: worker processes")
    parser.add_argument("--port", type=int, default=8877, help="own server: port")
    parser.add_argument("--broker", default="memory", help="own server: 'memory' or redis://...")
    args = parser.parse_args()
    rows = []
    for k in args.devices:
        if args.server:
            rows.append(measure(args.server, args.key, args.pid, k, args.seconds, args.warmup))
        else:
            with _own_server(args.port, args.workers, args.broker) as (url, pid):
                rows.append(measure(url, ADMIN, pid, k, args.seconds, args.warmup))
    where = args.server or f"own server, broker={args.broker}, workers={args.workers}"
    print(f"\n{where}: {args.seconds:.0f} s per row after {args.warmup:.0f} s warm-up, "
          "every request ?wait=true; latencies in ms from the batch's send")  # fmt: skip
    print(" ".join(f"{c:>9}" for c in rows[0]))
    for row in rows:
        print(" ".join(f"{v:>9.0f}" if isinstance(v, int) else f"{v:>9.1f}" for v in row.values()))


if __name__ == "__main__":
    main()
