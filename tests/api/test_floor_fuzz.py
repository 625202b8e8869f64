"""Random floor maps (outlines of every size from micrometres to thousands of kilometres,
in degrees, crossing themselves, with features far away or malformed) never get a 500:
each is stored or refused with a 422 whose every problem has a reason."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.state import _settings as settings_dependency

CASES = 160
RASTER_BUDGET = 400_000
"""Cells an accepted map may rasterise to here: keeps the run to seconds, not the limit."""


def _ring(rng: np.random.Generator, centre: np.ndarray, scale: float) -> list[list[float]]:
    """Return a closed ring: star-shaped (valid), or its points shuffled (often crossing)."""
    n = int(rng.integers(3, 12))
    angles = np.sort(rng.uniform(0, 2 * math.pi, n))
    radii = scale * rng.uniform(0.2, 1.0, n)
    points = centre + np.c_[radii * np.cos(angles), radii * np.sin(angles)]
    if rng.random() < 0.3:
        points = rng.permutation(points)
    if rng.random() < 0.1:
        points[1] = points[0]  # a repeated point
    ring = points.round(6).tolist()
    return [*ring, ring[0]]


def _geometry(rng: np.random.Generator, kind: str, centre: np.ndarray, scale: float) -> Any:
    """Return a geometry of the kind's type, now and then of the wrong shape or type."""
    roll = rng.random()
    if roll < 0.03:
        return {"type": "Polygon", "coordinates": []}
    if roll < 0.06:
        return {"type": "Point", "coordinates": ["1", 2]}
    if roll < 0.08:
        return {"type": "LineString", "coordinates": [[0, 0]]}
    if kind in ("transmitter", "anchor", "locator"):
        xy = centre + rng.uniform(-scale, scale, 2)
        return {"type": "Point", "coordinates": [*xy.round(6).tolist(), 2.5]}
    if kind == "wall":
        points = centre + rng.uniform(-scale, scale, (int(rng.integers(2, 5)), 2))
        return {"type": "LineString", "coordinates": points.round(6).tolist()}
    polygon = [_ring(rng, centre, scale)]
    if kind in ("outline", "barrier") and rng.random() < 0.15:
        other = centre + rng.uniform(-3, 3, 2) * scale
        return {"type": "MultiPolygon", "coordinates": [polygon, [_ring(rng, other, scale)]]}
    return {"type": "Polygon", "coordinates": polygon}


def random_map(rng: np.random.Generator) -> dict[str, Any]:
    """Return one random floor map: its outline's size and place drawn over many decades."""
    # half of them the size of a building (2 to 100 m), the others anything
    scale = 10 ** (rng.uniform(0.3, 2) if rng.random() < 0.5 else rng.uniform(-6, 7))
    if rng.random() < 0.2:
        # longitude/latitude degrees, a building's few hundredths of a degree or less
        centre = np.array([rng.uniform(-180, 180), rng.uniform(-90, 90)])
        scale = 10 ** rng.uniform(-5, -1)
    else:
        centre = scale * np.array([1.0, 1.0]) + rng.normal(0, 10 ** rng.uniform(-3, 7), 2)
    features = [{"type": "Feature", "properties": {"kind": "outline"},
                 "geometry": _geometry(rng, "outline", centre, scale)}]  # fmt: skip
    for index in range(int(rng.integers(0, 8))):
        kind = str(rng.choice(["wall", "barrier", "zone", "room", "transmitter", "anchor"]))
        # most features near the outline, some at another scale or far away
        where = centre if rng.random() < 0.8 else centre + 10 ** rng.uniform(0, 8)
        size = scale if rng.random() < 0.8 else 10 ** rng.uniform(-3, 6)
        props: dict[str, Any] = {"kind": kind, "name": f"area {index}", "id": f"x{index}"}
        if kind == "transmitter":
            props["tech"] = "ble"
        features.append(
            {"type": "Feature", "properties": props, "geometry": _geometry(rng, kind, where, size)}
        )
    if rng.random() < 0.05:
        features.append(features[0])  # a second outline
    return {"type": "FeatureCollection", "properties": {"level": 0}, "features": features}


@pytest.fixture
def small_raster_budget(client: TestClient, settings: Settings) -> Iterator[None]:
    """The app with a raster budget that keeps each accepted map's raster small."""
    budget = settings.model_copy(update={"floor_max_raster_cells": RASTER_BUDGET})
    client.app.dependency_overrides[settings_dependency] = lambda: budget  # type: ignore[attr-defined]
    yield
    client.app.dependency_overrides.pop(settings_dependency)  # type: ignore[attr-defined]


def test_random_floor_maps_are_stored_or_refused_never_a_500(
    client: TestClient, admin: dict, site_id: str, small_raster_budget: None
) -> None:
    rng = np.random.default_rng(19)
    outcomes: dict[int, int] = {}
    for case in range(CASES):
        doc = random_map(rng)
        r = client.put(
            f"/v1/sites/{site_id}/floors/F{case}", content=json.dumps(doc), headers=admin
        )
        outcomes[r.status_code] = outcomes.get(r.status_code, 0) + 1
        assert r.status_code in (201, 422), (case, r.text, doc)
        if r.status_code == 422:
            details = r.json()["error"]["details"]
            assert details and all(isinstance(d["reason"], str) and d["reason"] for d in details)
    # the run reached both sides: maps stored, and maps refused
    assert outcomes.get(201, 0) >= 10 and outcomes.get(422, 0) >= 10, outcomes
