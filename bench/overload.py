"""Overload: far more devices than the server sustains for a minute, then a light load.

Runs ``--devices`` simulated devices posting at 1 Hz without waiting for their
positions (input arrives on schedule whatever the backlog; ``--wait`` for the
closed loop of ``bench/load.py``) against a server of its own (or
``--server``/``--pid``),
sampling the server's resident memory (API and workers) every second. Prints
the answers by status (202 or 200, 429, other), the drops the server counted, the
memory at start, its peak and its end; then, after the overload stops, runs
``--after`` devices for ``--recovery`` seconds and prints their latency and
failures, to show the server recovered.

    python bench/overload.py --devices 3000 --seconds 60 --overload-policy reject
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app import demo  # noqa: E402
from bench.load import (  # noqa: E402
    ADMIN,
    Tally,
    _children,
    _dropped,
    _own_server,
    _rss_mb,
    start_devices,
)


async def _drive(
    url: str, key: str, devices: int, seconds: float, pids: list[int], prefix: str, wait: bool
) -> tuple[Tally, list[float]]:
    """Run the devices for ``seconds`` while sampling the server's RSS once a second."""
    tally = Tally()
    until = time.monotonic() + seconds
    tasks = start_devices(url, key, devices, seconds, tally, prefix, wait)
    rss = []
    while time.monotonic() < until:
        rss.append(_rss_mb(pids))
        await asyncio.sleep(1.0)
    await asyncio.gather(*tasks)
    rss.append(_rss_mb(pids))
    return tally, rss


def run(url: str, key: str, pid: int, args: argparse.Namespace) -> None:
    """Overload, then recover; print the figures."""
    pids = [pid, *_children(pid)]
    idle_rss = _rss_mb(pids)
    dropped0 = _dropped(url, key)
    tally, rss = asyncio.run(_drive(url, key, args.devices, args.seconds, pids, "over", args.wait))
    accepted = 200 if args.wait else 202
    statuses = Counter(accepted for _ in tally.http) + Counter(s for _, s in tally.errors)
    dropped = _dropped(url, key) - dropped0
    time.sleep(args.pause)
    after_rss = _rss_mb(pids)
    calm, _ = asyncio.run(_drive(url, key, args.after, args.recovery, pids, "calm", True))
    calm_ms = np.array([v for _, v in calm.http]) * 1000
    loop = "waiting for positions" if args.wait else "not waiting"
    print(f"\noverload: {args.devices} devices at 1 Hz, {loop}, for {args.seconds:.0f} s")
    print(
        "answers: "
        + ", ".join(f"{status}: {n}" for status, n in sorted(statuses.items()))
        + f"; server-counted drops: {dropped:.0f}"
    )
    print(
        f"RSS (MB): idle {idle_rss:.1f}, peak {max(rss):.1f}, at the end {rss[-1]:.1f}, "
        f"{args.pause:.0f} s later {after_rss:.1f}"
    )
    print(
        f"recovery: {args.after} devices for {args.recovery:.0f} s: {calm_ms.size} answered 200, "
        f"{len(calm.errors)} failed, p50 {np.percentile(calm_ms, 50):.1f} ms, "
        f"p99 {np.percentile(calm_ms, 99):.1f} ms"
    )


def main() -> None:
    """Parse the options and run against our own server or a given one."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", help="URL of a running server (default: start one)")
    parser.add_argument("--key", default=os.environ.get("LOCUS_ADMIN_KEY"), help="admin key")
    parser.add_argument("--pid", type=int, help="the running server's pid")
    parser.add_argument("--devices", type=int, default=3000)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--pause", type=float, default=10.0, help="seconds between the phases")
    parser.add_argument("--after", type=int, default=50, help="devices in the recovery phase")
    parser.add_argument("--recovery", type=float, default=20.0)
    parser.add_argument("--workers", type=int, default=2, help="own server: worker processes")
    parser.add_argument("--port", type=int, default=8879, help="own server: port")
    parser.add_argument("--wait", action="store_true", help="devices wait for their positions")
    parser.add_argument("--overload-policy", choices=("reject", "latest"), default="reject")
    args = parser.parse_args()
    if args.server and args.pid is None:
        parser.error("--pid (the server's process id) is needed with --server")
    if args.server:
        run(args.server, args.key, args.pid, args)
        return
    os.environ["LOCUS_OVERLOAD_POLICY"] = args.overload_policy
    with _own_server(args.port, args.workers, "memory") as (url, pid):
        demo.install(url, ADMIN)
        run(url, ADMIN, pid, args)


if __name__ == "__main__":
    main()
