"""Soak: K devices at 1 Hz for a long time against a real `locus serve`; RSS over time.

    python bench/soak.py --devices 500 --minutes 30 --workers 2

Prints the resident memory (the API and its child processes, MB, and each
one's) every ``--every`` seconds, the request rate and latency of each
interval, and the memory trend (MB/hour, least-squares slope over the second
half of the run, after warm-up) of the whole and of each process, so a growth
can be placed.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app import demo  # noqa: E402
from bench.load import (  # noqa: E402
    ADMIN,
    Tally,
    _children,
    _own_server,
    _rss_mb,
    _until_built,
    quiet_collector,
    start_devices,
)

Sample = tuple[float, float, float, float, float, int, tuple[float, ...]]
"""Seconds since start, RSS (MB), requests/s, p50 and p99 (ms), errors, each process's RSS."""


async def _soak(
    url: str, devices: int, seconds: float, every: float, pids: list[int]
) -> list[Sample]:
    quiet_collector()
    tally = Tally()
    until = time.monotonic() + seconds
    tasks = start_devices(url, ADMIN, devices, seconds, tally, "soak")
    series = []
    started = time.monotonic()
    seen = 0
    while time.monotonic() < until:
        await asyncio.sleep(every)
        window = np.array([v for _, v in tally.http[seen:]]) * 1000
        seen = len(tally.http)
        each = tuple(_rss_mb([pid]) for pid in pids)
        row = (
            time.monotonic() - started,
            sum(each),
            window.size / every,
            float(np.percentile(window, 50)) if window.size else float("nan"),
            float(np.percentile(window, 99)) if window.size else float("nan"),
            len(tally.errors),
            each,
        )
        series.append(row)
        print(
            f"{row[0]:8.0f} s  RSS {row[1]:7.1f} MB  {row[2]:7.1f} req/s  p50 {row[3]:6.1f} ms  "
            f"p99 {row[4]:7.1f} ms  errors {row[5]}  by process "
            + " / ".join(f"{mb:.1f}" for mb in each),
            flush=True,
        )
    await asyncio.gather(*tasks)
    return series


def main() -> None:
    """Run the soak and print the memory series and trend."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", type=int, default=500)
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--every", type=float, default=60.0, help="seconds between samples")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--port", type=int, default=8878)
    args = parser.parse_args()
    with _own_server(args.port, args.workers, "memory") as (url, pid):
        demo.install(url, ADMIN)
        asyncio.run(_until_built(url, ADMIN))
        pids = [pid, *_children(pid)]
        series = asyncio.run(_soak(url, args.devices, args.minutes * 60, args.every, pids))
    t = np.array([r[0] for r in series])
    rss = np.array([r[1] for r in series])
    each = np.array([r[6] for r in series])
    half = t >= t[-1] / 2

    def trend(values: np.ndarray) -> float:
        # least-squares MB/hour over the second half
        return np.polyfit(t[half] / 3600, values[half], 1)[0] if half.sum() >= 2 else float("nan")

    print(f"\ndevices={args.devices} workers={args.workers} minutes={args.minutes}")
    print(
        f"RSS start {rss[0]:.1f} MB, end {rss[-1]:.1f} MB, peak {rss.max():.1f} MB; "
        f"trend over the second half {trend(rss):+.1f} MB/hour"
    )
    # the API and its children: the workers (and any helper process it started)
    names = ["API", *(f"child {pid}" for pid in pids[1:])]
    for name, column in zip(names, each.T, strict=True):
        print(
            f"  {name}: {column[0]:.1f} → {column[-1]:.1f} MB (peak {column.max():.1f}), "
            f"trend {trend(column):+.1f} MB/hour"
        )


if __name__ == "__main__":
    main()
