"""The track fit as it runs in a pool process: floor plan cached per map version."""

from __future__ import annotations

import math
import time
from functools import lru_cache
from typing import Any

import numpy as np

from app.engine.plan import FloorPlan
from app.engine.trackfit.fit import TrackFitParams, fit_track
from app.geometry.floormap import parse_floor_map
from app.geometry.raster import floor_plan


@lru_cache(maxsize=8)
def _plan(site_id: str, floor_id: str, version: int, doc_json: str, cell: float) -> FloorPlan:
    import json

    return floor_plan(parse_floor_map(json.loads(doc_json)), cell=cell)


def run_fit(job: dict[str, Any]) -> dict[str, Any]:
    """Fit one track; return status, points, score and elapsed time (never raises)."""
    started = time.perf_counter()
    try:
        plan = _plan(job["site_id"], job["floor_id"], job["version"], job["floor_doc"], job["cell"])
        request = job["request"]
        segments = request["segments"]
        defaults = TrackFitParams()
        params = TrackFitParams(
            grid=request.get("grid") or defaults.grid,
            scales=tuple(request.get("scales") or defaults.scales),
            turns=tuple(request.get("turns") or defaults.turns),
            time_limit_s=job["time_limit_s"],
        )
        heading = request.get("heading")
        # API heading: degrees clockwise from +y; engine direction: radians CCW from +x
        direction = None if heading is None else math.radians(90.0 - heading)
        fit = fit_track(
            plan,
            np.array([request["start"]["x"], request["start"]["y"]]),
            np.array([s["length"] for s in segments]),
            np.array([s["turn"] for s in segments]),
            heading=direction,
            params=params,
        )
    except Exception as exc:  # a fit that cannot run must still finish as failed
        return {
            "status": "failed",
            "error": f"{type(exc).__name__}: {exc}",
            "elapsed_ms": (time.perf_counter() - started) * 1000,
        }
    times = [request["t0"], *(s["t"] for s in segments)]
    points = [
        {"t": int(t), "x": round(float(x), 3), "y": round(float(y), 3)}
        for t, (x, y) in zip(times, fit.points, strict=False)
    ]
    return {
        "status": "failed" if fit.failed else "done",
        "error": fit.failed,
        "points": points,
        "score": fit.score,
        "elapsed_ms": (time.perf_counter() - started) * 1000,
        "grid": params.grid,
    }
