"""Measure the BLE flat through a running server: beacons calibrated by the site's own build.

What a deployment sees: a site with the flat's outline and its six anchors
mapped by position only (no path loss), the robot's test track replayed as a
phone posting its BLE readings in one-second batches with ``?wait=true``
(the weighted centroid is all an uncalibrated site can do), then the four
calibration runs uploaded as surveys (the robot's positions as waypoints),
the radio-map build fitting every anchor's A, B and σ, and the same track
replayed again as another device (now the particle filter on the fits).
Errors are against the robot's LiDAR position interpolated at each
position's time.

Run ``locus eval ble-flat-http --server URL --key ADMIN_KEY`` against a
running ``locus serve``.
"""

from __future__ import annotations

import argparse
import os
import uuid
from dataclasses import dataclass
from typing import Any, Protocol

import httpx
import numpy as np

from app.datasets import ble_flat

FLOOR = "flat"


class Http(Protocol):
    """What the replay needs of an HTTP client (httpx's, or a test's)."""

    def put(self, url: str, *, json: Any) -> httpx.Response: ...

    def post(self, url: str, *, json: Any = None) -> httpx.Response: ...


@dataclass(frozen=True)
class FlatRun:
    """Errors (m) before and after the build, the methods that placed each, and its summary."""

    before: np.ndarray
    before_methods: set[str]
    after: np.ndarray
    after_methods: set[str]
    summary: dict[str, Any]


def beacon_id(anchor: int) -> str:
    """Return the MAC address the flat's anchor ``anchor`` is mapped and reported under."""
    return f"F1:A7:00:00:00:{anchor:02X}"


def floor_map(anchors: ble_flat.Anchors) -> dict[str, Any]:
    """Return the flat's floor map: its outline and the anchors by position only."""
    outline = ble_flat.read_layout().tolist()
    features: list[dict[str, Any]] = [
        {
            "type": "Feature",
            "properties": {"kind": "outline"},
            "geometry": {"type": "Polygon", "coordinates": [outline]},
        }
    ]
    for anchor, (x, y, z) in zip(anchors.ids, anchors.xyz.tolist(), strict=True):
        features.append(
            {
                "type": "Feature",
                "properties": {
                    "kind": "transmitter",
                    "id": beacon_id(anchor),
                    "tech": "ble",
                    "z": z,
                },
                "geometry": {"type": "Point", "coordinates": [x, y]},
            }
        )
    return {"type": "FeatureCollection", "properties": {"level": 0}, "features": features}


def ble_samples(track: ble_flat.Track, anchors: ble_flat.Anchors) -> list[dict[str, Any]]:
    """Return the track's readings as the ingest's ``ble`` samples, in time order."""
    row, col = np.nonzero(np.isfinite(track.rssi))
    return [
        {
            "t": int(track.t[r]),
            "id": beacon_id(anchors.ids[c]),
            "rssi": round(float(track.rssi[r, c]), 2),
        }
        for r, c in zip(row.tolist(), col.tolist(), strict=True)
    ]


def survey_body(run: ble_flat.Track, anchors: ble_flat.Anchors) -> dict[str, Any]:
    """Return a calibration run as a survey: the robot's positions are its waypoints."""
    waypoints = [
        {"t": t, "x": x, "y": y} for t, (x, y) in zip(run.t.tolist(), run.xy.tolist(), strict=True)
    ]
    return {
        "device_id": "robot",
        "floor_id": FLOOR,
        "waypoints": waypoints,
        "ble": ble_samples(run, anchors),
    }


def replay(
    http: Http, site_id: str, device_id: str, track: ble_flat.Track, anchors: ble_flat.Anchors
) -> tuple[np.ndarray, set[str]]:
    """Post the track's readings in one-second batches; return its positions' errors (m)
    against the robot's and the methods that placed it."""
    samples = ble_samples(track, anchors)
    second = [(s["t"] - samples[0]["t"]) // 1000 for s in samples]
    positions: list[dict[str, Any]] = []
    for k in sorted(set(second)):
        batch = [s for s, at in zip(samples, second, strict=True) if at == k]
        body = {"device_id": device_id, "site_id": site_id, "ble": batch}
        r = http.post("/v1/ingest?wait=true", json=body)
        r.raise_for_status()
        positions += r.json()["positions"]
    t = np.array([p["t"] for p in positions])
    xy = np.array([[p["x"], p["y"]] for p in positions]).reshape(-1, 2)
    errors = np.linalg.norm(xy - ble_flat.truth_at(track, t), axis=1)
    return errors, {p["method"] for p in positions}


def measure(http: Http, *, seconds: float | None = None) -> FlatRun:
    """Set up a new flat site, replay the test track (its first ``seconds``), build the site
    from the calibration runs and replay the track again."""
    anchors = ble_flat.read_anchors()
    test = ble_flat.test_robot()
    if seconds is not None:
        test = test.slice(slice(0, int(np.searchsorted(test.t, test.t[0] + seconds * 1000))))
    site_id = f"ble-flat-{uuid.uuid4().hex[:6]}"
    http.put(f"/v1/sites/{site_id}", json={"name": "BLE flat"}).raise_for_status()
    http.put(f"/v1/sites/{site_id}/floors/{FLOOR}", json=floor_map(anchors)).raise_for_status()
    before, before_methods = replay(http, site_id, f"{site_id}-before", test, anchors)
    for run in ble_flat.runs(ble_flat.calibration()):
        http.post(f"/v1/sites/{site_id}/surveys", json=survey_body(run, anchors)).raise_for_status()
    r = http.post(f"/v1/sites/{site_id}/radiomap/build")
    r.raise_for_status()
    after, after_methods = replay(http, site_id, f"{site_id}-after", test, anchors)
    return FlatRun(before, before_methods, after, after_methods, r.json())


def main(argv: list[str] | None = None) -> None:
    """Print the error before and after the build, and the build's fits."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", default="http://127.0.0.1:8000")
    parser.add_argument("--key", default=os.environ.get("LOCUS_ADMIN_KEY"), help="admin key")
    args = parser.parse_args(argv)
    headers = {"Authorization": f"Bearer {args.key}"}
    with httpx.Client(base_url=args.server, headers=headers, timeout=300) as http:
        run = measure(http)
    print("BLE flat over HTTP: the robot's test track, horizontal error (m)")
    print(
        f"{'site':>28} {'method':>7} {'positions':>9} {'mean':>6} {'p50':>6} {'p75':>6} {'p95':>6}"
    )
    for name, e, methods in (
        ("anchors by position only", run.before, run.before_methods),
        ("after the radio-map build", run.after, run.after_methods),
    ):
        p50, p75, p95 = np.quantile(e, [0.5, 0.75, 0.95])
        method = ",".join(sorted(methods))
        print(
            f"{name:>28} {method:>7} {e.size:>9} {np.mean(e):6.3f} {p50:6.3f} {p75:6.3f} {p95:6.3f}"
        )
    print(f"{'anchor':>18} {'A':>8} {'B':>7} {'sigma':>6} {'readings':>8}")
    for fit in run.summary["calibration"]["transmitters"]:
        print(
            f"{fit['id']:>18} {fit['A']:8.2f} {fit['B']:7.2f} {fit['sigma']:6.2f} "
            f"{fit['n_readings']:>8}"
        )


if __name__ == "__main__":
    main()
