"""First position of a new device on site1, on a freshly started server.

Loads site1's five mall floors (``maps/site1``, access points placed every
15 m: ``bench/site1.py``) into a server, stops it, and starts a fresh one on
the same database, with the workers warming every site at start
(``LOCUS_WARM_SITES=true``, the default) and without (built on a device's
first batch, as before). Then, per run, times from the moment a new device's
first batch is sent (two WiFi scans a second apart, ``?wait=true``) until a
position comes back: for the first device on the fresh server, a second
device, and a device after the site's map changed (a floor uploaded again,
then ``--settle`` seconds). Prints a table:

    python -m bench.first_position --workers 2 --runs 3
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bench.site1 import floor_maps, scan, walkable_point

ADMIN = "lk_bench-f1rst-p0s1t10n-adm1n-K3y"
SITE = "site1"


class Server:
    """A ``locus serve`` subprocess on a free port, its log in ``home``."""

    def __init__(self, home: Path, workers: int, env: dict[str, str]) -> None:
        port = _free_port()
        self.url = f"http://127.0.0.1:{port}"
        started = time.perf_counter()
        self.process = subprocess.Popen(
            [sys.executable, "-m", "app.cli", "serve", "--port", str(port),
             "--workers", str(workers), "--home", str(home)],
            stdout=(home / "serve.log").open("a"), stderr=subprocess.STDOUT,
            env=os.environ | {"LOCUS_ADMIN_KEY": ADMIN} | env,
        )  # fmt: skip
        while True:
            if self.process.poll() is not None:
                raise RuntimeError((home / "serve.log").read_text()[-2000:])
            try:
                if httpx.get(self.url + "/readyz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.05)
        self.ready_s = time.perf_counter() - started
        self.http = httpx.Client(
            base_url=self.url, headers={"Authorization": f"Bearer {ADMIN}"}, timeout=120
        )

    def stop(self) -> None:
        """Stop the server and wait for it."""
        self.http.close()
        self.process.terminate()
        self.process.wait(timeout=60)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def first_position_ms(server: Server, doc: dict[str, Any], device: str, seed: int) -> float:
    """Return the ms from sending a new device's first batch to its first position."""
    rng = np.random.default_rng(seed)
    xy = walkable_point(doc, rng)
    t0 = 1_700_000_000_000 + seed * 10_000_000
    started = time.perf_counter()
    for k in range(0, 20, 2):
        wifi = scan(doc, xy, t0 + 1000 * k, rng) + scan(doc, xy, t0 + 1000 * (k + 1), rng)
        body = {"device_id": device, "site_id": SITE, "wifi": wifi}
        r = server.http.post("/v1/ingest?wait=true", json=body)
        r.raise_for_status()
        if r.json()["positions"]:
            return (time.perf_counter() - started) * 1000
    raise RuntimeError(f"{device}: no position after 20 s of scans")


def run(workers: int, warm: bool, runs: int, settle: float) -> dict[str, float]:
    """Time the first positions ``runs`` times on fresh servers; return the medians."""
    maps = floor_maps()
    env = {"LOCUS_WARM_SITES": "true" if warm else "false"}
    figures: dict[str, list[float]] = {"ready": [], "first": [], "second": [], "changed": []}
    with tempfile.TemporaryDirectory(prefix="locus-first-") as tmp:
        home = Path(tmp)
        setup = Server(home, workers, env)
        setup.http.put(f"/v1/sites/{SITE}", json={"name": "ILC site1"}).raise_for_status()
        for floor, doc in maps.items():
            setup.http.put(f"/v1/sites/{SITE}/floors/{floor}", json=doc).raise_for_status()
        setup.stop()
        for i in range(runs):
            server = Server(home, workers, env)
            try:
                figures["ready"].append(server.ready_s)
                figures["first"].append(first_position_ms(server, maps["F1"], f"a{i}", 3 * i))
                figures["second"].append(first_position_ms(server, maps["F2"], f"b{i}", 3 * i + 1))
                put = server.http.put(f"/v1/sites/{SITE}/floors/F3", json=maps["F3"])
                put.raise_for_status()
                time.sleep(settle)
                figures["changed"].append(first_position_ms(server, maps["F3"], f"c{i}", 3 * i + 2))
            finally:
                server.stop()
    return {k: statistics.median(v) for k, v in figures.items()}


def main(argv: list[str] | None = None) -> None:
    """Run with and without warm sites and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--runs", type=int, default=3, help="fresh servers per setting")
    parser.add_argument(
        "--settle", type=float, default=3.0, help="seconds between a map change and the device"
    )
    args = parser.parse_args(argv)
    aps = sum(
        1 for d in floor_maps().values() for f in d["features"]
        if f["properties"]["kind"] == "transmitter"
    )  # fmt: skip
    print(f"site1: 5 floors, {aps} access points; {args.workers} workers; median of {args.runs}")
    print("| sites built | ready s | first device ms | second device ms | after a change ms |")
    print("|---|---|---|---|---|")
    for warm in (True, False):
        m = run(args.workers, warm, args.runs, args.settle)
        label = "at start and on change" if warm else "on a device's first batch"
        print(
            f"| {label} | {m['ready']:.2f} | {m['first']:.0f} | {m['second']:.0f} "
            f"| {m['changed']:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
