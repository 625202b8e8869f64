"""Replay recordings through a Locus server's HTTP API and score its positions.

This is how a client sees Locus: batches of one second of measurement time
posted with ``?wait=true``; the positions that come back are compared with
the recording's surveyed truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np

from app.datasets.ilc import Walk
from app.evaluation.metrics import truth_at
from app.importers.ilc import walk_samples


@dataclass(frozen=True)
class Scored:
    """Positions of one replayed walk with their errors against the truth."""

    positions: list[dict[str, Any]]
    errors: np.ndarray
    floor_ok: np.ndarray


def batches_by_time(
    samples: dict[str, list[dict[str, Any]]], *, batch_ms: int
) -> list[dict[str, list[dict[str, Any]]]]:
    """Cut sample lists into consecutive windows of ``batch_ms`` measurement time."""
    times = [s["t"] for items in samples.values() for s in items]
    if not times:
        return []
    start = min(times)
    out: dict[int, dict[str, list[dict[str, Any]]]] = {}
    for kind, items in samples.items():
        for s in items:
            out.setdefault((s["t"] - start) // batch_ms, {}).setdefault(kind, []).append(s)
    return [out[k] for k in sorted(out)]


def replay_walk(
    http: httpx.Client, walk: Walk, *, site_id: str, device_id: str, batch_ms: int = 1000
) -> list[dict[str, Any]]:
    """Post the walk's samples batch by batch with ``?wait=true``; return every position."""
    positions: list[dict[str, Any]] = []
    for chunk in batches_by_time(walk_samples(walk), batch_ms=batch_ms):
        body = {"device_id": device_id, "site_id": site_id, **chunk}
        r = http.post("/v1/ingest?wait=true", json=body)
        r.raise_for_status()
        positions += r.json()["positions"]
    return positions


def score(walk: Walk, positions: list[dict[str, Any]]) -> Scored:
    """Return horizontal errors (on the right floor) and the floor hits of positions."""
    inside = [p for p in positions if walk.waypoints[0, 0] <= p["t"] <= walk.waypoints[-1, 0]]
    if not inside:
        return Scored(positions, np.zeros(0), np.zeros(0, dtype=bool))
    t = np.array([p["t"] for p in inside])
    xy = np.array([[p["x"], p["y"]] for p in inside])
    truth, _ = truth_at(walk.waypoints, t)
    floor_ok = np.array([p["floor_id"] == walk.floor for p in inside])
    errors = np.linalg.norm(xy - truth, axis=1)[floor_ok]
    return Scored(inside, errors, floor_ok)
