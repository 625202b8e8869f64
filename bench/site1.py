"""Site1's five mall floors (``maps/site1``) with access points on a grid, and scans in them.

The floor maps come without transmitters (the mall's are learned from its
surveys), so a site made of them alone positions nothing. Placing calibrated
access points every ``spacing`` metres over each floor's walkable area gives
the mall's full rasters and a particle filter to run on them, without the
surveys and the radio-map build.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from app.geometry.floormap import parse_floor_map

MAPS = Path(__file__).resolve().parents[1] / "maps" / "site1"
FLOORS = ("B1", "F1", "F2", "F3", "F4")
A_DBM, B_DB, SIGMA_DB = -40.0, 12.0, 4.0
"""Path loss of every placed access point: ``rssi = A - B ln r`` with noise ``sigma`` (dB)."""


def _ap_id(floor: int, k: int) -> str:
    return f"02:51:00:{floor:02x}:{k // 256:02x}:{k % 256:02x}"


def floor_maps(spacing: float = 15.0) -> dict[str, dict[str, Any]]:
    """Return site1's floor maps by floor id, each with access points every ``spacing`` m."""
    maps = {}
    for f, name in enumerate(FLOORS):
        doc = json.loads((MAPS / f"{name}.geojson").read_text())
        walkable = parse_floor_map(doc).walkable
        xmin, ymin, xmax, ymax = walkable.bounds
        xs, ys = np.meshgrid(np.arange(xmin, xmax, spacing), np.arange(ymin, ymax, spacing))
        inside = shapely.contains_xy(walkable, xs.ravel(), ys.ravel())
        points = np.column_stack([xs.ravel(), ys.ravel()])[inside]
        doc["features"] += [
            {
                "type": "Feature",
                "properties": {
                    "kind": "transmitter",
                    "id": _ap_id(f, k),
                    "tech": "wifi",
                    "A": A_DBM,
                    "B": B_DB,
                    "sigma": SIGMA_DB,
                },
                "geometry": {"type": "Point", "coordinates": [round(x, 2), round(y, 2), 3.0]},
            }
            for k, (x, y) in enumerate(points)
        ]
        maps[name] = doc
    return maps


def scan(
    doc: dict[str, Any], xy: tuple[float, float], t: int, rng: np.random.Generator
) -> list[dict[str, Any]]:
    """Return the WiFi readings a phone at ``xy`` on ``doc``'s floor hears at ``t`` (ms)."""
    readings = []
    for feature in doc["features"]:
        props = feature["properties"]
        if props["kind"] != "transmitter":
            continue
        x, y, z = feature["geometry"]["coordinates"]
        r = max(0.5, float(np.hypot(np.hypot(x - xy[0], y - xy[1]), z - 1.2)))
        # rssi = A - B ln r + ε
        rssi = props["A"] - props["B"] * np.log(r) + props["sigma"] * rng.standard_normal()
        if rssi > -90:
            readings.append({"t": t, "id": props["id"], "rssi": round(float(rssi), 1)})
    return readings


def walkable_point(doc: dict[str, Any], rng: np.random.Generator) -> tuple[float, float]:
    """Return a random point of the floor's walkable area."""
    walkable = parse_floor_map(doc).walkable
    xmin, ymin, xmax, ymax = walkable.bounds
    while True:
        x, y = rng.uniform(xmin, xmax), rng.uniform(ymin, ymax)
        if shapely.contains_xy(walkable, x, y):
            return float(x), float(y)
