"""Measure locator mode through a running server: the BLE locator tracks replayed over HTTP.

What a deployment sees: for each of the 5 tracks (leave one track out) a
site with one open floor of the 20.7 × 17.6 m area and the 12 locators at
their known 3-D positions, carrying the path loss (A, B, σ per locator)
fitted on the other 4 tracks. The held-out track's sightings are then posted
as each locator would report them: one ``POST /v1/ingest/locator?wait=true``
per locator and second of measurement time, in time order. The tag's
positions are read back from its stored history and compared with the
truth interpolated at each position's time. The server runs its own defaults
(tag height, fix σ floor); the in-process evaluation
(``locus eval locator``) tunes those on the training tracks instead.

Run ``locus eval locator-http --server URL --key ADMIN_KEY`` against a
running ``locus serve``.
"""

from __future__ import annotations

import argparse
import os
import uuid
from typing import Any

import httpx
import numpy as np

from app.datasets.ble_locator import Locators, Track, read_locators, read_track, track_names
from app.evaluation.locator_eval import fit_path_loss, truth_at
from app.replay import history

AREA_M = (20.7, 17.6)
"""Extent of the recorded area (m): the floor's outline."""


def floor_map(locators: Locators, A: np.ndarray, B: np.ndarray, sigma: np.ndarray) -> dict:
    """Return the one-floor map: the area's outline and every locator with its path loss."""
    w, h = AREA_M
    features: list[dict[str, Any]] = [
        {
            "type": "Feature",
            "properties": {"kind": "outline"},
            "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [w, 0], [w, h], [0, h]]]},
        }
    ]
    for k, loc_id in enumerate(locators.ids):
        x, y, z = (round(float(v), 3) for v in locators.xyz[k])
        features.append(
            {
                "type": "Feature",
                "properties": {
                    "kind": "locator",
                    "id": loc_id,
                    "A": round(float(A[k]), 3),
                    "B": round(float(B[k]), 3),
                    "sigma": round(float(sigma[k]), 3),
                },
                "geometry": {"type": "Point", "coordinates": [x, y, z]},
            }
        )
    return {"type": "FeatureCollection", "properties": {"level": 0}, "features": features}


def locator_bodies(track: Track, locators: Locators, site_id: str, tag_id: str) -> list[dict]:
    """Cut a track into the per-locator, per-second reports a gateway would post, in time order."""
    second = (track.t - track.t[0]) // 1000
    bodies = []
    for s in np.unique(second):
        in_second = second == s
        for k in np.unique(track.locator[in_second]):
            rows = np.flatnonzero(in_second & (track.locator == k))
            sightings = [
                {"t": int(track.t[i]), "tag_id": tag_id, "rssi": float(track.rssi[i])} for i in rows
            ]
            bodies.append(
                {"site_id": site_id, "locator_id": locators.ids[k], "sightings": sightings}
            )
    return bodies


def replay_track(
    http: httpx.Client, track: Track, train: list[Track], locators: Locators
) -> np.ndarray:
    """Set up a site for the held-out track, post its sightings, return the horizontal errors."""
    site_id = f"ble-locator-{uuid.uuid4().hex[:6]}"
    tag_id = f"{site_id}-tag"
    pl = fit_path_loss(train, locators, pooled=False)
    http.put(
        f"/v1/sites/{site_id}", json={"name": f"BLE locators ({track.name})"}
    ).raise_for_status()
    http.put(
        f"/v1/sites/{site_id}/floors/area", json=floor_map(locators, pl.A, pl.B, pl.sigma)
    ).raise_for_status()
    for body in locator_bodies(track, locators, site_id, tag_id):
        http.post("/v1/ingest/locator?wait=true", json=body).raise_for_status()
    positions = history(http, site_id, tag_id, t_from=int(track.t[0]))
    t = np.array([p["t"] for p in positions], dtype=float)
    xy = np.array([[p["x"], p["y"]] for p in positions]).reshape(-1, 2)
    return np.hypot(*(xy - truth_at(track, t)).T)


def main(argv: list[str] | None = None) -> None:
    """Print the mean and 75th percentile error per held-out track, replayed over HTTP."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", default="http://127.0.0.1:8000")
    parser.add_argument("--key", default=os.environ.get("LOCUS_ADMIN_KEY"), help="admin key")
    args = parser.parse_args(argv)

    locators = read_locators()
    names = track_names()
    tracks = {n: read_track(n, locators) for n in names}
    headers = {"Authorization": f"Bearer {args.key}"}
    errors = {}
    with httpx.Client(base_url=args.server, headers=headers, timeout=60) as http:
        for name in names:
            train = [tracks[n] for n in names if n != name]
            errors[name] = replay_track(http, tracks[name], train, locators)
    print("locator mode over HTTP: horizontal error (m) per held-out track")
    print(f"{'track':>26} {'positions':>9} {'mean':>6} {'p75':>6}")
    for name in [*names, "all"]:
        e = np.concatenate(list(errors.values())) if name == "all" else errors[name]
        print(f"{name:>26} {e.size:>9} {np.mean(e):6.2f} {np.quantile(e, 0.75):6.2f}")


if __name__ == "__main__":
    main()
