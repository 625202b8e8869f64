"""Load benchmark: K devices sending one batch a second to a running `locus serve`.

Drives the server at ``--server`` (with an admin ``--key``) from this separate
process: installs the demo site if it is missing, subscribes to the site's
positions on the WebSocket, then runs K simulated devices (random routes on
the demo floor, BLE scans from the path-loss model) for a fixed time, in each
of the ``--modes``:

- ``http``: one keep-alive connection per device, one ``POST /v1/ingest`` per batch;
- ``bulk``: one connection per 100 devices, one ``POST /v1/ingest/bulk`` a second
  carrying those devices' batches of that second;
- ``ws``: one ``/v1/ws/ingest`` socket per device, one message per batch.

Every batch is sent with ``?wait=true`` (each device waits for its answer
before its next batch). Prints one row per mode and K: requests and device
updates per second (updates also as a ratio to the ``/healthz`` rate, measured
first with the same client, closed loop, so every figure reads against what the
HTTP stack itself does), p50/p99 of the answer and of the position's arrival on
the positions WebSocket (both from the batch's send), failed batches, positions
the server dropped (``/metrics``), the CPU of the server's API process, of its
workers and of this generator (% of one core), and the server's RSS.

``--saturate C`` first runs plain HTTP closed loop without the 1 Hz pacing (C
connections, each cycling through its share of ``--saturate-devices``), then a
paced ``http`` row at 80% of the rate it reached, and says whether p99 stays
within 100 ms there and whether saturation reaches half the ``/healthz`` rate.

    locus serve --port 8000 --workers 2 &
    python bench/load.py --server http://127.0.0.1:8000 --key ADMIN_KEY --pid PID \
        --devices 100 1000 5000 --seconds 20

Without ``--server`` it starts its own server per row (embedded SQLite, or
``--broker redis://...``) and stops it afterwards.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
import secrets
import subprocess
import sys
import tempfile
import time
import uuid
from bisect import bisect_right
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
import redis

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app import demo  # noqa: E402
from app.core.heap import settle_heap  # noqa: E402
from bench.wire import Connection, Socket  # noqa: E402

ADMIN = secrets.token_urlsafe(32)
"""The admin key of a server this benchmark starts itself."""
MODES = ("http", "bulk", "ws")
BULK = 100
"""Devices per bulk body."""
P99_TARGET_MS = 100.0


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


class Fleet:
    """K simulated devices walking the demo routes; each second's ingest body built cheaply.

    Plain-Python arithmetic on the demo's ten beacons costs a few microseconds a
    body, so 5,000 devices a second stay a small share of one core.
    """

    def __init__(self, count: int, prefix: str, t0: int) -> None:
        self.t0 = t0
        self.names = [f"{prefix}-{i}" for i in range(count)]
        self.beacons = [
            (*f["geometry"]["coordinates"][:2], p["A"], p["B"], p["sigma"], p["id"])
            for f in demo.load_map()["features"]
            if (p := f["properties"])["kind"] == "transmitter"
        ]
        self.rngs = [random.Random(name) for name in self.names]
        self.walks = []
        for rng in self.rngs:
            route = demo.ROUTES[rng.randrange(len(demo.ROUTES))]
            legs = [math.dist(a, b) for a, b in zip(route, route[1:], strict=False)]
            cumulative = [0.0, *np.cumsum(legs).tolist()]
            self.walks.append((route, cumulative, 1.0 + rng.random() * 0.4))

    def _at(self, i: int, k: int) -> tuple[float, float]:
        """Return device i's position after ``k`` seconds of walking (as demo.Walker)."""
        route, cumulative, speed = self.walks[i]
        s = (k * speed) % cumulative[-1]
        j = min(bisect_right(cumulative, s), len(route) - 1)
        (x0, y0), (x1, y1) = route[j - 1], route[j]
        f = (s - cumulative[j - 1]) / ((cumulative[j] - cumulative[j - 1]) or 1.0)
        return x0 + f * (x1 - x0), y0 + f * (y1 - y0)

    def body(self, i: int, k: int, t: int | None = None) -> str:
        """Return device i's ingest body for its k-th second: one BLE scan, at ``t`` (ms;
        by default ``k`` seconds after the fleet's ``t0``)."""
        x, y = self._at(i, k)
        t = self.t0 + 1000 * k if t is None else t
        gauss = self.rngs[i].gauss
        readings = []
        for bx, by, a, b, sigma, beacon in self.beacons:
            rssi = a - b * math.log(max(0.5, math.hypot(x - bx, y - by))) + gauss(0, sigma)
            if rssi > -95:
                readings.append(f'{{"t":{t},"id":"{beacon}","rssi":{rssi:.1f}}}')
        return (
            f'{{"device_id":"{self.names[i]}","site_id":"{demo.SITE_ID}",'
            f'"ble":[{",".join(readings)}]}}'
        )


@dataclass
class Tally:
    """What the devices and the WebSocket saw, each entry stamped with its perf-counter time."""

    http: list[tuple[float, float]] = field(default_factory=list)
    """Each device update answered: when, and its latency from the send."""
    ws: list[tuple[float, float]] = field(default_factory=list)
    errors: list[tuple[float, int]] = field(default_factory=list)
    requests: list[float] = field(default_factory=list)
    """When each request (or socket message) was answered."""
    last_sent: dict[str, float] = field(default_factory=dict)


def quiet_collector() -> None:
    """Keep this generator's cyclic collector from pausing it the way the server's is kept.

    The tallies grow by a tuple per answer; at Python's thresholds the generator
    paused for a full collection every 100 s (900 devices), 42 ms at first and up
    to 131 ms later, and its devices' next batches reached the server together, a
    burst the workers' memory then showed.
    """
    settle_heap()


Send = Callable[[int], Awaitable[None]]
"""Send one second's batches of a device (or a bulk group) and tally the answers."""


async def _paced(send: Send, until: float) -> None:
    """Call ``send(k)`` once a second; a late sender does not burst to catch up."""
    await asyncio.sleep(random.random())
    start = time.monotonic()
    k = 0
    while time.monotonic() < until:
        await send(k)
        k += 1
        await asyncio.sleep(max(0.0, start + k - time.monotonic()))


def _http_sender(conn: Connection, fleet: Fleet, i: int, tally: Tally, wait: bool) -> Send:
    path = "/v1/ingest?wait=true" if wait else "/v1/ingest"
    name = fleet.names[i]

    async def send(k: int) -> None:
        body = fleet.body(i, k).encode()
        sent = time.perf_counter()
        tally.last_sent[name] = sent
        try:
            status = await conn.post(path, body)
        except (OSError, asyncio.IncompleteReadError):
            conn.close()
            status = 0
        done = time.perf_counter()
        tally.requests.append(done)
        if status in (200, 202):
            tally.http.append((done, done - sent))
        else:
            tally.errors.append((done, status))

    return send


def _bulk_sender(conn: Connection, fleet: Fleet, group: range, tally: Tally) -> Send:
    async def send(k: int) -> None:
        body = '{"batches":[' + ",".join(fleet.body(i, k) for i in group) + "]}"
        sent = time.perf_counter()
        for i in group:
            tally.last_sent[fleet.names[i]] = sent
        try:
            status, answer = await conn.request("POST", "/v1/ingest/bulk?wait=true", body.encode())
        except (OSError, asyncio.IncompleteReadError):
            conn.close()
            status, answer = 0, b""
        done = time.perf_counter()
        tally.requests.append(done)
        if status != 200:
            tally.errors.extend((done, status) for _ in group)
            return
        for result in json.loads(answer)["results"]:
            if result["status"] == 200:
                tally.http.append((done, done - sent))
            else:
                tally.errors.append((done, result["status"]))

    return send


def _ws_sender(sock: Socket, fleet: Fleet, i: int, tally: Tally) -> Send:
    name = fleet.names[i]

    async def send(k: int) -> None:
        sent = time.perf_counter()
        tally.last_sent[name] = sent
        sock.send(fleet.body(i, k).encode())
        try:
            answer = await sock.receive()
        except (OSError, EOFError, asyncio.IncompleteReadError):
            answer = b'{"status":0}'
        done = time.perf_counter()
        tally.requests.append(done)
        if b'"error"' in answer:
            tally.errors.append((done, json.loads(answer).get("status", 0)))
        else:
            tally.http.append((done, done - sent))

    return send


async def _open_sockets(host: str, port: int, key: str, count: int) -> list[Socket]:
    """Open ``count`` ingest sockets, a hundred handshakes at a time."""
    gate = asyncio.Semaphore(100)

    async def one() -> Socket:
        async with gate:
            return await Socket.open(host, port, f"/v1/ws/ingest?wait=true&key={key}")

    return await asyncio.gather(*(one() for _ in range(count)))


def start_devices(url: str, key: str, devices: int, seconds: float, tally: Tally,
                  prefix: str, wait: bool = True) -> list[asyncio.Task[None]]:  # fmt: skip
    """Start K simulated devices posting at 1 Hz over plain HTTP for ``seconds``.

    With ``wait`` each device waits for its positions before its next batch (a closed
    loop); without, batches leave on schedule whatever the server's backlog.
    """
    host, port = url.removeprefix("http://").split(":")
    fleet = Fleet(devices, prefix, int(time.time() * 1000) - 3_600_000)
    until = time.monotonic() + seconds
    return [
        asyncio.create_task(
            _paced(_http_sender(Connection(host, int(port), key), fleet, i, tally, wait), until)
        )
        for i in range(devices)
    ]


async def _senders(url: str, key: str, mode: str, fleet: Fleet, tally: Tally) -> list[Send]:
    """Return the mode's senders for the fleet: one per device, or one per bulk group."""
    host, port = url.removeprefix("http://").split(":")
    count = len(fleet.names)
    if mode == "http":
        conns = [Connection(host, int(port), key) for _ in range(count)]
        return [_http_sender(c, fleet, i, tally, True) for i, c in enumerate(conns)]
    if mode == "bulk":
        groups = [range(g, min(g + BULK, count)) for g in range(0, count, BULK)]
        return [_bulk_sender(Connection(host, int(port), key), fleet, g, tally) for g in groups]
    sockets = await _open_sockets(host, int(port), key, count)
    return [_ws_sender(s, fleet, i, tally) for i, s in enumerate(sockets)]


async def _saturating(conn: Connection, fleet: Fleet, share: range, until: float,
                      tally: Tally) -> None:  # fmt: skip
    """Post the share's devices' batches back to back, each device a second further each round."""
    senders = [_http_sender(conn, fleet, i, tally, True) for i in share]
    k = 0
    while time.monotonic() < until:
        for send in senders:
            await send(k)
        k += 1


async def _watch(url: str, key: str, tally: Tally) -> None:
    """Stamp every position of the site arriving on the WebSocket against its batch's send."""
    host, port = url.removeprefix("http://").split(":")
    sock = await Socket.open(host, int(port), f"/v1/ws/positions?site_id={demo.SITE_ID}&key={key}")
    try:
        while True:
            raw = await sock.receive()
            now = time.perf_counter()
            msg = json.loads(raw)
            sent = tally.last_sent.get(msg.get("device_id", ""))
            if msg.get("type") == "position" and sent is not None:
                tally.ws.append((now, now - sent))
    finally:
        sock.close()


async def healthz_rate(url: str, key: str, connections: int = 4, seconds: float = 8.0) -> float:
    """Return ``GET /healthz`` answers per second, closed loop over a few keep-alive
    connections: the rate the HTTP stack reaches with nothing behind it."""
    host, port = url.removeprefix("http://").split(":")
    until = time.monotonic() + seconds
    answered = [0]

    async def loop() -> None:
        conn = Connection(host, int(port), key)
        while time.monotonic() < until:
            status, _ = await conn.request("GET", "/healthz")
            answered[0] += status == 200
        conn.close()

    started = time.monotonic()
    await asyncio.gather(*(loop() for _ in range(connections)))
    return answered[0] / (time.monotonic() - started)


@dataclass
class Usage:
    """CPU seconds of the server's API process, of its workers and of this generator."""

    api: float
    workers: float
    generator: float
    at: float

    @classmethod
    def now(cls, pids: list[int]) -> Usage:
        """Read the counters of ``pids`` (the API first) and of this process."""
        api = _cpu_seconds(pids[:1])
        return cls(api, _cpu_seconds(pids[1:]), time.process_time(), time.monotonic())


async def _run(url: str, key: str, mode: str, devices: int, seconds: float, warmup: float,
               pids: list[int], saturate: int) -> tuple[Tally, float, Usage, Usage]:  # fmt: skip
    """Run one row; return the tally, when the measurement began and the CPU at its ends."""
    quiet_collector()
    tally = Tally()
    watcher = asyncio.create_task(_watch(url, key, tally))
    await asyncio.sleep(0.5)
    fleet = Fleet(devices, f"load-{uuid.uuid4().hex[:6]}", int(time.time() * 1000) - 3_600_000)
    if saturate:
        host, port = url.removeprefix("http://").split(":")
        until = time.monotonic() + warmup + seconds
        runs = [
            _saturating(
                Connection(host, int(port), key), fleet, range(c, devices, saturate), until, tally
            )
            for c in range(saturate)
        ]
    else:
        senders = await _senders(url, key, mode, fleet, tally)
        until = time.monotonic() + warmup + seconds
        runs = [_paced(send, until) for send in senders]
    started = time.perf_counter()
    tasks = [asyncio.create_task(r) for r in runs]
    await asyncio.sleep(warmup)
    begin = Usage.now(pids)
    await asyncio.sleep(seconds)
    end = Usage.now(pids)
    await asyncio.gather(*tasks)
    await asyncio.sleep(0.5)
    watcher.cancel()
    return tally, started + warmup, begin, end


async def _until_built(url: str, key: str, limit_s: float = 180.0) -> None:
    """Wait until a few devices' batches come back within 250 ms: a worker builds a site it
    has not seen before its first batch is processed, which takes seconds, not a row's warm-up."""
    host, port = url.removeprefix("http://").split(":")
    fleet = Fleet(8, f"built-{uuid.uuid4().hex[:6]}", int(time.time() * 1000) - 3_600_000)
    conns = [Connection(host, int(port), key) for _ in fleet.names]
    deadline = time.monotonic() + limit_s
    k = 0
    while time.monotonic() < deadline:
        started = time.perf_counter()
        answers = await asyncio.gather(
            *(
                c.post("/v1/ingest?wait=true", fleet.body(i, k).encode())
                for i, c in enumerate(conns)
            )
        )
        k += 1
        if set(answers) == {200} and time.perf_counter() - started < 0.25:
            break
        await asyncio.sleep(0.5)
    for c in conns:
        c.close()


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


def measure(url: str, key: str, pid: int | None, mode: str, devices: int, seconds: float,
            warmup: float, healthz: float, saturate: int = 0) -> dict[str, object]:  # fmt: skip
    """Run K devices in ``mode`` against the server at ``url``; return the row of figures."""
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"}) as http:
        if http.get(f"/v1/sites/{demo.SITE_ID}").status_code == 404:
            demo.install(url, key)
    asyncio.run(_until_built(url, key))
    pids = [] if pid is None else [pid, *_children(pid)]
    dropped0 = _dropped(url, key)
    tally, since, begin, end = asyncio.run(
        _run(url, key, mode, devices, seconds, warmup, pids, saturate)
    )
    wall = end.at - begin.at
    http_ms = np.array([v for t, v in tally.http if t >= since]) * 1000
    ws_ms = np.array([v for t, v in tally.ws if t >= since]) * 1000

    def pct(a: np.ndarray, q: float) -> float:
        return float(np.percentile(a, q)) if a.size else float("nan")

    def share(cpu: float) -> float:
        return cpu / wall * 100 if pids else float("nan")

    return {
        "mode": f"{mode}-sat{saturate}" if saturate else mode,
        "devices": devices,
        "req/s": sum(1 for t in tally.requests if t >= since) / seconds,
        "upd/s": http_ms.size / seconds,
        "x hz": http_ms.size / seconds / healthz,
        "ans p50": pct(http_ms, 50),
        "ans p99": pct(http_ms, 99),
        "pos p50": pct(ws_ms, 50),
        "pos p99": pct(ws_ms, 99),
        "failed": sum(1 for t, _ in tally.errors if t >= since),
        "dropped": _dropped(url, key) - dropped0,
        "API %": share(end.api - begin.api),
        "wrk %": share(end.workers - begin.workers),
        "gen %": (end.generator - begin.generator) / wall * 100,
        "RSS MB": _rss_mb(pids) if pids else float("nan"),
    }


def _cell(v: object) -> str:
    if isinstance(v, str):
        return f"{v:>9}"
    if isinstance(v, int):
        return f"{v:>9d}"
    assert isinstance(v, float)
    return f"{v:>9.2f}" if abs(v) < 10 else f"{v:>9.1f}"


def main() -> None:
    """Measure /healthz, the saturation if asked, then each mode and device count; print."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", help="URL of a running server (default: start one per row)")
    parser.add_argument("--key", default=os.environ.get("LOCUS_ADMIN_KEY"), help="admin key")
    parser.add_argument("--pid", type=int, help="the running server's pid, for CPU and RSS")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--devices", type=int, nargs="*", default=[100, 1000, 2000, 5000])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--warmup", type=float, default=5.0)
    parser.add_argument("--saturate", type=int, default=0, metavar="C",
                        help="first run plain HTTP closed loop over C connections")  # fmt: skip
    parser.add_argument("--saturate-devices", type=int, default=200)
    parser.add_argument("--workers", type=int, default=2, help="own server: worker processes")
    parser.add_argument("--port", type=int, default=8877, help="own server: port")
    parser.add_argument("--broker", default="memory", help="own server: 'memory' or redis://...")
    args = parser.parse_args()

    @contextmanager
    def server() -> Iterator[tuple[str, str, int | None]]:
        if args.server:
            yield args.server, args.key, args.pid
        else:
            with _own_server(args.port, args.workers, args.broker) as (url, pid):
                yield url, ADMIN, pid

    def row(mode: str, devices: int, saturate: int = 0) -> dict[str, object]:
        with server() as (url, key, pid):
            return measure(url, key, pid, mode, devices, args.seconds, args.warmup, healthz,
                           saturate)  # fmt: skip

    with server() as (url, key, _):
        healthz = asyncio.run(healthz_rate(url, key))
    rows = []
    if args.saturate:
        rows.append(row("http", args.saturate_devices, args.saturate))
    rows.extend(row(mode, k) for mode in args.modes for k in args.devices)
    if args.saturate:
        saturation = float(rows[0]["upd/s"])  # type: ignore[arg-type]
        rows.append(row("http", round(0.8 * saturation)))
    where = args.server or f"own server, broker={args.broker}, workers={args.workers}"
    print(f"\n{where}: {args.seconds:.0f} s per row after {args.warmup:.0f} s warm-up, every "
          "batch ?wait=true; latencies in ms from the batch's send (ans: its answer, pos: its "
          "position on the positions WebSocket); ws: one socket per device")  # fmt: skip
    print(f"/healthz: {healthz:.0f} req/s (4 keep-alive connections, closed loop, 8 s)")
    print(" ".join(f"{c:>9}" for c in rows[0]))
    for r in rows:
        print(" ".join(_cell(v) for v in r.values()))
    if args.saturate:
        at80 = rows[-1]
        p99 = float(at80["pos p99"])  # type: ignore[arg-type]
        print(
            f"plain-HTTP saturation {saturation:.0f} updates/s = {saturation / healthz:.2f} x "
            f"/healthz (at least half: {'yes' if saturation >= healthz / 2 else 'no'}); "
            f"at 80% ({at80['devices']} devices at 1 Hz) position p99 {p99:.1f} ms "
            f"(within {P99_TARGET_MS:.0f} ms: {'yes' if p99 <= P99_TARGET_MS else 'no'})"
        )


if __name__ == "__main__":
    main()
