"""The demo site: a small office plan and simulated devices walking in it.

``locus demo`` serves Locus with this site loaded and a handful of simulated
devices posting BLE scans and UWB ranges through the public HTTP API, so the
dashboard comes alive at once.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np

log = logging.getLogger(__name__)

DEMO_MAP = Path(__file__).resolve().parents[1] / "maps" / "demo-office.geojson"
SITE_ID = "demo"
FLOOR_ID = "F1"

# Routes through the office (corridor along y = 10, rooms above and below).
ROUTES = [
    [(3, 10), (37, 10), (33, 10), (33, 16), (29, 17), (33, 16), (33, 10), (3, 10)],
    [
        (5, 10),
        (15, 10),
        (15, 4),
        (12, 5),
        (15, 4),
        (15, 10),
        (23, 10),
        (23, 16),
        (20, 17),
        (23, 16),
        (23, 10),
        (5, 10),
    ],
    [(36, 10), (23, 10), (23, 4), (20, 3), (23, 4), (23, 10)],
]


def load_map() -> dict[str, Any]:
    """Return the demo floor map."""
    return json.loads(DEMO_MAP.read_text())


def _emitters(doc: dict[str, Any], kind: str) -> list[dict[str, Any]]:
    return [
        {"xyz": f["geometry"]["coordinates"], **f["properties"]}
        for f in doc["features"]
        if f["properties"]["kind"] == kind
    ]


class Walker:
    """A simulated person following a looping route at walking speed."""

    def __init__(self, route: Sequence[tuple[float, float]], speed: float) -> None:
        self.points = np.array(route, dtype=float)
        legs = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.cumulative = np.concatenate([[0.0], np.cumsum(legs)])
        self.speed = speed

    def at(self, seconds: float) -> np.ndarray:
        """Return the position after walking ``seconds``."""
        s = (seconds * self.speed) % self.cumulative[-1]
        return np.array([np.interp(s, self.cumulative, self.points[:, k]) for k in range(2)])


def simulate(
    base_url: str,
    key: str,
    *,
    stop: threading.Event,
    on_running: Callable[[], None] = lambda: None,
    seed: int = 1,
) -> None:
    """Post one batch a second per simulated device until ``stop`` is set.

    The first round waits for its positions, so the workers have loaded the site (and
    said so) when ``on_running`` is called.
    """
    doc = load_map()
    beacons = _emitters(doc, "transmitter")
    anchors = _emitters(doc, "anchor")
    walkers = {f"phone-{k + 1}": Walker(route, 1.0 + 0.15 * k) for k, route in enumerate(ROUTES)}
    tag = Walker(ROUTES[0][::-1], 0.8)
    rng = np.random.default_rng(seed)
    started = time.time()
    with httpx.Client(base_url=base_url, headers={"Authorization": f"Bearer {key}"}) as http:
        first = True
        while not stop.wait(1.0):
            now = int(time.time() * 1000)
            elapsed = time.time() - started
            for device, walker in walkers.items():
                xy = walker.at(elapsed)
                ble = []
                for b in beacons:
                    r = max(0.5, float(np.hypot(*(xy - b["xyz"][:2]))))
                    # rssi = A - B ln r + noise
                    rssi = b["A"] - b["B"] * np.log(r) + b["sigma"] * rng.standard_normal()
                    if rssi > -95:
                        ble.append({"t": now, "id": b["id"], "rssi": round(float(rssi), 1)})
                body = {"device_id": device, "site_id": SITE_ID, "ble": ble}
                _post(http, body, wait=first)
            xy = np.append(tag.at(elapsed), 1.0)
            ranges = np.linalg.norm(xy - np.array([a["xyz"] for a in anchors]), axis=1)
            ranges += 0.05 * rng.standard_normal(len(anchors))
            uwb = [
                {"t": now, "anchor": a["id"], "range": round(float(r), 3), "std": 0.1}
                for a, r in zip(anchors, ranges, strict=True)
            ]
            _post(http, {"device_id": "tag-1", "site_id": SITE_ID, "uwb": uwb}, wait=first)
            if first:
                on_running()
                first = False


def _post(http: httpx.Client, body: dict[str, Any], *, wait: bool) -> None:
    try:
        http.post("/v1/ingest", params={"wait": "true"} if wait else None, json=body, timeout=30)
    except httpx.HTTPError as exc:
        log.warning("demo device %s: %s", body["device_id"], exc)


def base_url(host: str, port: int) -> str:
    """Return the URL a browser on this machine opens for a server bound to ``host``."""
    shown = "127.0.0.1" if host in ("0.0.0.0", "", "::") else host
    return f"http://{shown}:{port}"


def banner(base: str, key: str) -> str:
    """Return the box the demo prints once it runs: where to look and the key to sign in."""
    lines = [
        "Locus demo is running.",
        "",
        f"  Dashboard   {base}/",
        f"  Admin key   {key}",
        f"  API docs    {base}/docs",
        "",
        "Sign in to the dashboard with the admin key. Ctrl-C stops the demo.",
    ]
    width = max(len(line) for line in lines)
    rule = "─" * (width + 2)
    body = "\n".join(f"│ {line.ljust(width)} │" for line in lines)
    return f"\n╭{rule}╮\n{body}\n╰{rule}╯\n"


def install(base_url: str, key: str) -> None:
    """Create the demo site and floor through the API (idempotent)."""
    with httpx.Client(base_url=base_url, headers={"Authorization": f"Bearer {key}"}) as http:
        http.put(f"/v1/sites/{SITE_ID}", json={"name": "Demo office"}).raise_for_status()
        http.put(f"/v1/sites/{SITE_ID}/floors/{FLOOR_ID}", json=load_map()).raise_for_status()
