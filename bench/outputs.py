"""Outputs benchmark: what an MQTT output costs ingest, and how late its messages arrive.

Starts a ``locus serve`` of its own on a fresh home twice: once without outputs, once with
an MQTT output of the demo site (positions and zone events) to the local Mosquitto
(``--broker``). In each, ``--devices`` simulated devices (``bench.load``'s fleet: BLE
scans on the demo floor) send one batch a second through bulk ingest (100 devices a
body, ``?wait=true``) for ``--seconds`` after ``--warmup``: the answers' p50 and p99 from
each body's send. Then the same devices post closed loop, each connection of
``--connections`` sending its next body once the last is answered: the saturation rate in
device updates per second and its answer p99. During the 1 Hz run a listener in a process
of its own stamps each position's receipt on the positions WebSocket and, with the output,
from a subscriber to the broker: the lag runs from the position's time (the devices stamp
their scans with the wall clock as they send them) to its receipt, so the WebSocket's is
the engine's own and the MQTT one's less that is what the output adds. ``--repeats``
alternates the two servers; prints a Markdown table of every run and the best saturation
with the output as a share of the best without:

    python -m bench.outputs --seconds 30
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import secrets
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection as Pipe
from multiprocessing.synchronize import Event
from urllib.parse import urlsplit

import httpx
import numpy as np

from app import demo
from bench.load import BULK, Fleet, _children, _cpu_seconds, _until_built, quiet_collector
from bench.wire import Connection

ADMIN = secrets.token_urlsafe(32)
BUDGET = 0.20
"""Most of ingest's saturation rate an output may cost."""


def listener(ws_url: str, broker: str | None, topic: str, ready: Event, stop: Event,
             out: Pipe) -> None:  # fmt: skip
    """Until ``stop``, stamp each position arriving on the positions WebSocket and, given a
    ``broker``, on the MQTT ``topic`` (QoS 1); send back both lists of (receipt epoch ms,
    lag ms from the position's ``t``)."""
    import threading

    import paho.mqtt.client as mqtt
    from websockets.sync.client import connect

    socket_lags: list[tuple[float, float]] = []
    mqtt_lags: list[tuple[float, float]] = []

    def stamp(into: list[tuple[float, float]], raw: bytes | str) -> None:
        now = time.time() * 1000
        message = json.loads(raw)
        if message.get("type") == "position":
            into.append((now, now - message["t"]))

    def watch() -> None:
        with connect(ws_url) as ws:
            subscribed.set()
            while not stop.is_set():
                try:
                    stamp(socket_lags, ws.recv(timeout=0.5))
                except TimeoutError:
                    continue

    subscribed = threading.Event()
    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    client = None
    if broker is not None:
        parts = urlsplit(broker)
        client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        client.on_message = lambda c, u, m: stamp(mqtt_lags, m.payload)
        confirmed = threading.Event()
        client.on_subscribe = lambda *args: confirmed.set()
        client.connect(parts.hostname or "127.0.0.1", parts.port or 1883)
        client.subscribe(topic, qos=1)
        client.loop_start()
        confirmed.wait(30)
    subscribed.wait(30)
    ready.set()
    stop.wait()
    if client is not None:
        client.loop_stop()
        client.disconnect()
    watcher.join(5)
    out.send((socket_lags, mqtt_lags))


@contextmanager
def serve(port: int, workers: int, database_url: str | None) -> Iterator[tuple[str, int]]:
    """Run ``locus serve`` on a fresh home (and its own SQLite, unless a database is given);
    yield its URL and pid."""
    with tempfile.TemporaryDirectory() as home:
        argv = [sys.executable, "-m", "app.cli", "serve", "--port", str(port), "--workers",
                str(workers), "--home", home]  # fmt: skip
        if database_url:
            argv += ["--database-url", database_url]
        server = subprocess.Popen(
            argv,
            env=os.environ | {"LOCUS_ADMIN_KEY": ADMIN},
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        url = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 120
            while True:
                try:
                    if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                if time.monotonic() > deadline or server.poll() is not None:
                    raise RuntimeError("locus serve did not become ready")
                time.sleep(0.3)
            yield url, server.pid
        finally:
            server.terminate()
            server.wait(timeout=60)


@dataclass
class Answers:
    """Each answered body's (perf-counter time, latency s, device updates accepted)."""

    rows: list[tuple[float, float, int]]

    def between(self, t0: float, t1: float) -> Answers:
        """Return the answers from ``t0`` to ``t1`` (perf-counter seconds)."""
        return Answers([r for r in self.rows if t0 <= r[0] < t1])

    def rate(self, seconds: float) -> float:
        """Return the device updates answered per second."""
        return sum(n for _, _, n in self.rows) / seconds

    def percentile(self, q: float) -> float:
        """Return the latency percentile in ms."""
        if not self.rows:
            return float("nan")
        return float(np.percentile([lat for _, lat, _ in self.rows], q)) * 1000


async def _post(conn: Connection, body: str, answers: Answers) -> None:
    sent = time.perf_counter()
    try:
        status, answer = await conn.request("POST", "/v1/ingest/bulk?wait=true", body.encode())
    except (OSError, asyncio.IncompleteReadError):
        conn.close()
        return
    done = time.perf_counter()
    if status == 200:
        ok = sum(r["status"] == 200 for r in json.loads(answer)["results"])
        answers.rows.append((done, done - sent, ok))


def _body(fleet: Fleet, group: range, k: int, t: int) -> str:
    return '{"batches":[' + ",".join(fleet.body(i, k, t) for i in group) + "]}"


async def paced(url: str, fleet: Fleet, seconds: float) -> tuple[Answers, int]:
    """Send every device's batch once a second, stamped with the wall clock, for
    ``seconds``; return the answers and the last second's index."""
    host, port = url.removeprefix("http://").split(":")
    count = len(fleet.names)
    groups = [range(g, min(g + BULK, count)) for g in range(0, count, BULK)]
    answers = Answers([])
    start = time.monotonic()
    steps = int(seconds)

    async def group_loop(g: int, group: range) -> None:
        conn = Connection(host, int(port), ADMIN)
        # the groups spread over the second, as devices' clocks are
        await asyncio.sleep(g / len(groups))
        for k in range(steps):
            await _post(conn, _body(fleet, group, k, int(time.time() * 1000)), answers)
            await asyncio.sleep(max(0.0, start + g / len(groups) + k + 1 - time.monotonic()))
        conn.close()

    await asyncio.gather(*(group_loop(g, group) for g, group in enumerate(groups)))
    return answers, steps


async def saturated(url: str, fleet: Fleet, first: int, seconds: float, connections: int,
                    t0: int) -> Answers:  # fmt: skip
    """Post the devices' next seconds back to back over ``connections``, each a body of
    100 devices at a time, for ``seconds``; return the answers."""
    host, port = url.removeprefix("http://").split(":")
    count = len(fleet.names)
    groups = [range(g, min(g + BULK, count)) for g in range(0, count, BULK)]
    answers = Answers([])
    until = time.monotonic() + seconds

    async def loop(c: int) -> None:
        conn = Connection(host, int(port), ADMIN)
        mine = groups[c::connections]
        k = first
        while time.monotonic() < until:
            for group in mine:
                await _post(conn, _body(fleet, group, k, t0 + 1000 * (k - first)), answers)
            k += 1
        conn.close()

    await asyncio.gather(*(loop(c) for c in range(connections)))
    return answers


def metric(url: str, name: str) -> float:
    """Return the sum of a /metrics family's samples."""
    text = httpx.get(url + "/metrics", headers={"Authorization": f"Bearer {ADMIN}"}).text
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines() if line.startswith(name))


def run(args: argparse.Namespace, with_output: bool) -> dict[str, object]:
    """Measure one server: the 1 Hz run, then saturation; return the row."""
    quiet_collector()
    with serve(args.port, args.workers, args.database_url) as (url, pid):
        demo.install(url, ADMIN)
        prefix = f"bench{uuid.uuid4().hex[:8]}"
        if with_output:
            body = {"kind": "mqtt", "url": args.broker, "topic_prefix": prefix}
            put = httpx.put(
                f"{url}/v1/sites/{demo.SITE_ID}/outputs/bench",
                json=body,
                headers={"Authorization": f"Bearer {ADMIN}"},
            )
            put.raise_for_status()
        ctx = mp.get_context("spawn")
        ready, stop = ctx.Event(), ctx.Event()
        lag_pipe, sender = ctx.Pipe(duplex=False)
        ws_url = f"ws{url.removeprefix('http')}/v1/ws/positions?site_id={demo.SITE_ID}&key={ADMIN}"
        topic = f"{prefix}/{demo.SITE_ID}/devices/+/position"
        watching = ctx.Process(
            target=listener,
            args=(ws_url, args.broker if with_output else None, topic, ready, stop, sender),
        )
        watching.start()
        if not ready.wait(60):
            raise RuntimeError("the WebSocket or the broker did not take the subscription")
        asyncio.run(_until_built(url, ADMIN))
        fleet = Fleet(args.devices, f"out-{uuid.uuid4().hex[:6]}", 0)
        pids = [pid, *_children(pid)]

        begin = time.perf_counter() + args.warmup
        begin_ms = (time.time() + args.warmup) * 1000
        answers, steps = asyncio.run(paced(url, fleet, args.warmup + args.seconds))
        at_rate = answers.between(begin, begin + args.seconds)
        time.sleep(2.0)  # the last second's positions on their way
        stop.set()
        socket_lags, mqtt_lags = (
            np.array([lag for at, lag in lags if at >= begin_ms]) for lags in lag_pipe.recv()
        )
        watching.join(10)

        cpu0 = _cpu_seconds(pids[:1]), _cpu_seconds(pids[1:])
        wall0 = time.monotonic()
        t0 = int(time.time() * 1000) + 1000
        full = asyncio.run(saturated(url, fleet, steps, args.seconds, args.connections, t0))
        wall = time.monotonic() - wall0
        api_cpu = (_cpu_seconds(pids[:1]) - cpu0[0]) / wall * 100
        worker_cpu = (_cpu_seconds(pids[1:]) - cpu0[1]) / wall * 100
        pending = metric(url, "locus_output_pending")
        delivered = metric(url, "locus_output_delivered_total")

    def pct(a: np.ndarray, q: float) -> float:
        return float(np.percentile(a, q)) if a.size else float("nan")

    return {
        "output": "MQTT (positions, zones)" if with_output else "none",
        "1 Hz upd/s": at_rate.rate(args.seconds),
        "1 Hz p50 ms": at_rate.percentile(50),
        "1 Hz p99 ms": at_rate.percentile(99),
        "saturation upd/s": full.rate(wall),
        "sat. p99 ms": full.percentile(99),
        "API CPU %": api_cpu,
        "workers CPU %": worker_cpu,
        "WS lag p50 ms": pct(socket_lags, 50),
        "WS lag p99 ms": pct(socket_lags, 99),
        "MQTT lag p50 ms": pct(mqtt_lags, 50),
        "MQTT lag p99 ms": pct(mqtt_lags, 99),
        "delivered": int(delivered),
        "pending after": int(pending),
    }


def _cell(value: object) -> str:
    if isinstance(value, float):
        return "–" if value != value else f"{value:.0f}" if abs(value) >= 100 else f"{value:.1f}"
    return str(value)


def main() -> None:
    """Measure without and with the output; print the table and the share."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", type=int, default=1000)
    parser.add_argument("--seconds", type=float, default=30.0, help="each run's measured time")
    parser.add_argument("--warmup", type=float, default=5.0)
    parser.add_argument("--connections", type=int, default=10, help="saturation: connections")
    parser.add_argument("--repeats", type=int, default=1, help="pairs of runs, alternating")
    parser.add_argument("--workers", type=int, default=2, help="the server's worker processes")
    parser.add_argument("--port", type=int, default=8878)
    parser.add_argument("--broker", default="mqtt://127.0.0.1:1883", help="the MQTT output's")
    parser.add_argument("--database-url", help="default: the server's own SQLite")
    args = parser.parse_args()
    rows = [run(args, with_output=bool(k % 2)) for k in range(2 * args.repeats)]
    print(
        f"\n{args.devices} devices, bulk ingest ({BULK} a body, ?wait=true); {args.seconds:.0f} s "
        f"at 1 Hz and {args.seconds:.0f} s closed loop over {args.connections} connections "
        f"after {args.warmup:.0f} s; {args.workers} workers, "
        f"{'PostgreSQL' if args.database_url else 'SQLite'}\n"
    )
    print("| " + " | ".join(rows[0]) + " |")
    print("|" + "---|" * len(rows[0]))
    for row in rows:
        print("| " + " | ".join(_cell(v) for v in row.values()) + " |")

    def saturation(with_output: bool) -> float:
        # best of the repeats: what else runs on the machine only ever lowers a run's rate
        return max(float(r["saturation upd/s"]) for r in rows[with_output::2])  # type: ignore[arg-type]

    share = saturation(True) / saturation(False)
    print(
        f"\nsaturation with the output (best of {args.repeats} each): {share:.1%} of without "
        f"(within the {BUDGET:.0%} budget: {'yes' if share >= 1 - BUDGET else 'no'})"
    )


if __name__ == "__main__":
    main()
