"""Load benchmark: K devices posting one batch a second to a real `locus serve`.

Starts a server (embedded SQLite, N worker processes) on loopback, installs the
demo site, then runs K simulated devices for a fixed time. Every request uses
``?wait=true``, so its latency is ingest-to-position. Prints one row per K:
achieved request rate, p50/p99 latency, server CPU (API + workers, % of one
core) and peak RSS.

    python bench/load.py --devices 100 1000 5000 --seconds 30 --workers 2
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
from pathlib import Path

import httpx
import numpy as np
import redis

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app import demo  # noqa: E402

ADMIN = "lk_bench_admin"


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

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def post(self, path: str, body: bytes) -> int:
        """Send one POST and return the status code (the body is read and discarded)."""
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        head = (
            f"POST {path} HTTP/1.1\r\nHost: {self.host}\r\nAuthorization: Bearer {ADMIN}\r\n"
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


async def _device(
    http: Connection,
    name: str,
    beacons: list[dict],
    until: float,
    latencies: list[float],
    errors: list[int],
    t0: int,
) -> None:
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
        try:
            status = await http.post("/v1/ingest?wait=true", json.dumps(body).encode())
        except (OSError, asyncio.IncompleteReadError):
            http.writer = None
            status = 0
        if status == 200:
            latencies.append(time.perf_counter() - sent)
        else:
            errors.append(status)
        k += 1
        # keep a 1 Hz schedule; a late device does not burst to catch up
        await asyncio.sleep(max(0.0, start + k - time.monotonic()))


async def _run(
    url: str, devices: int, seconds: float, warmup: float
) -> tuple[list[float], list[int], float]:
    beacons = [
        {"xyz": f["geometry"]["coordinates"], **f["properties"]}
        for f in demo.load_map()["features"]
        if f["properties"]["kind"] == "transmitter"
    ]
    latencies: list[float] = []
    errors: list[int] = []
    t0 = int(time.time() * 1000) - 3_600_000
    host, port = url.removeprefix("http://").split(":")
    until = time.monotonic() + warmup + seconds
    tasks = [
        asyncio.create_task(
            _device(
                Connection(host, int(port)),
                f"load-{devices}-{i}",
                beacons,
                until,
                latencies,
                errors,
                t0,
            )
        )
        for i in range(devices)
    ]
    await asyncio.sleep(warmup)
    measured_from = len(latencies)
    started = time.monotonic()
    await asyncio.gather(*tasks)
    elapsed = time.monotonic() - started
    return latencies[measured_from:], errors, elapsed


def main() -> None:
    """Run the benchmark for each device count and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", type=int, nargs="+", default=[100, 1000, 5000])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--warmup", type=float, default=5.0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--port", type=int, default=8877)
    parser.add_argument(
        "--broker", default="memory", help="'memory' or redis://... (API node + local workers)"
    )
    args = parser.parse_args()
    rows = []
    for k in args.devices:
        if args.broker.startswith("redis"):
            redis.Redis.from_url(args.broker).flushdb()  # no streams or leases of a past run
        with tempfile.TemporaryDirectory() as home:
            env = os.environ | {"LOCUS_ADMIN_KEY": ADMIN}
            server = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "app.cli",
                    "serve",
                    "--port",
                    str(args.port),
                    "--workers",
                    str(args.workers),
                    "--home",
                    home,
                    "--broker",
                    args.broker,
                ],
                cwd=ROOT,
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            url = f"http://127.0.0.1:{args.port}"
            try:
                deadline = time.monotonic() + 60
                while time.monotonic() < deadline:
                    try:
                        if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                            break
                    except httpx.HTTPError:
                        time.sleep(0.3)
                demo.install(url, ADMIN)
                pids = [server.pid, *_children(server.pid)]
                cpu0 = _cpu_seconds(pids)
                latencies, errors, elapsed = asyncio.run(_run(url, k, args.seconds, args.warmup))
                cpu = (_cpu_seconds(pids) - cpu0) / (elapsed + args.warmup) * 100
                rss = _rss_mb(pids)
            finally:
                server.terminate()
                server.wait(timeout=60)
        lat = np.array(latencies) * 1000
        rows.append(
            (
                k,
                len(lat) / elapsed,
                np.percentile(lat, 50) if lat.size else float("nan"),
                np.percentile(lat, 99) if lat.size else float("nan"),
                len(errors),
                cpu,
                rss,
            )
        )
    print(
        f"\nbroker={args.broker}  workers={args.workers}  seconds={args.seconds}  "
        "(every request ?wait=true)"
    )
    columns = ("devices", "req/s", "p50 ms", "p99 ms", "errors", "CPU %", "RSS MB")
    print(" ".join(f"{c:>8}" for c in columns))
    for k, rate, p50, p99, err, cpu, rss in rows:
        print(f"{k:>8} {rate:>8.1f} {p50:>8.1f} {p99:>8.1f} {err:>8} {cpu:>8.0f} {rss:>8.0f}")


if __name__ == "__main__":
    main()
