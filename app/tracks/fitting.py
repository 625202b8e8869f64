"""The track fit as it runs in a pool process: floor plan and radio map cached per map version."""

from __future__ import annotations

import json
import math
import time
from dataclasses import replace
from functools import lru_cache
from typing import Any

import numpy as np

from app.core.heap import trim_allocator
from app.engine.plan import FloorPlan
from app.engine.radiomap import RadioMap
from app.engine.scan_knn import ReferenceScans, ScanKnnParams
from app.engine.trackfit.anchors import AnchorCosts, WifiScan, wifi_anchor_costs
from app.engine.trackfit.compass import fused_directions
from app.engine.trackfit.search import (
    Candidate,
    TrackSearch,
    TrackSearchParams,
    durations,
    rigid_tracks,
    search_track,
)
from app.engine.trackfit.verdict import Verdict, VerdictParams, judge
from app.geometry.floormap import parse_floor_map
from app.geometry.raster import floor_plan
from app.radiomaps.codec import decode_map


@lru_cache(maxsize=8)
def _plan(site_id: str, floor_id: str, version: int, doc_json: str, cell: float) -> FloorPlan:
    return floor_plan(parse_floor_map(json.loads(doc_json)), cell=cell)


@lru_cache(maxsize=8)
def _radio_map(
    site_id: str,
    floor_id: str,
    version: int,
    data: bytes,
    transmitters: tuple[str, ...],
    knn: ScanKnnParams,
) -> tuple[RadioMap, ReferenceScans | None, dict[str, int]]:
    """Decode a stored map with its columns numbered 0…, its survey scans prepared for
    the site's k-NN (None when the map keeps none) and the id → column lookup."""
    m = replace(decode_map(data), tx=np.arange(len(transmitters), dtype=np.int32))
    refs = None if m.references is None else ReferenceScans.from_maps((m,), len(transmitters), knn)
    return m, refs, {tx: i for i, tx in enumerate(transmitters)}


def _anchors(
    job: dict[str, Any], segments: list[dict[str, Any]], sigma: float
) -> AnchorCosts | None:
    """Return the cost rasters of the segments' scans on the floor's survey scans, if the
    floor has a radio map that keeps them."""
    stored = job.get("radiomap")
    if not stored:
        return None
    radio_map, refs, column = _radio_map(
        job["site_id"],
        job["floor_id"],
        job["version"],
        stored["data"],
        tuple(stored["transmitters"]),
        ScanKnnParams(**stored.get("knn", {})),
    )
    if refs is None:
        return None
    scans = []
    for i, segment in enumerate(segments, start=1):
        known = [r for r in segment.get("wifi") or () if r["id"] in column]
        if known:
            tx = np.array([column[r["id"]] for r in known], dtype=np.int64)
            scans.append(WifiScan(i, tx, np.array([r["rssi"] for r in known], dtype=float)))
    return wifi_anchor_costs(radio_map, refs, scans, sigma) if scans else None


def _heading_deg(direction: float) -> float:
    """Engine direction (rad, CCW from +x) → API heading (degrees clockwise from +y)."""
    return round((90.0 - math.degrees(direction)) % 360.0, 2)


def _candidate(c: Candidate, points: list[dict[str, Any]] | None) -> dict[str, Any]:
    return {
        "rotation": _heading_deg(c.rotation),
        "scale": round(c.scale, 3),
        "drift": round(math.degrees(c.drift), 3),
        "score": round(c.score, 4),
        "points": points,
    }


def _points(
    times: list[int], xy: np.ndarray, radius: np.ndarray | None = None
) -> list[dict[str, Any]]:
    out = [
        {"t": int(t), "x": round(float(x), 3), "y": round(float(y), 3)}
        for t, (x, y) in zip(times, xy, strict=False)
    ]
    if radius is not None:
        for point, r in zip(out, radius, strict=False):
            point["radius"] = round(float(r), 3)
    return out


DEFAULT_HEADING_SIGMA_DEG = 10.0
"""σ of one per-link compass heading when the track does not say (indoors, a few to tens
of degrees)."""


def _compass(segments: list[dict[str, Any]]) -> np.ndarray | None:
    """Return the per-link headings as engine directions (rad, CCW from +x; NaN where a link
    has none), or None when no link has one."""
    given = [s.get("heading") for s in segments]
    if all(h is None for h in given):
        return None
    return np.array([np.nan if h is None else math.radians(90.0 - h) for h in given])


def placed_track(
    found: TrackSearch,
    start: np.ndarray,
    lengths: np.ndarray,
    turns: np.ndarray,
    *,
    heading: float | None,
    compass: np.ndarray | None,
    sigma: float,
    dt: np.ndarray,
    params: TrackSearchParams,
) -> np.ndarray:
    """Return the uploaded track placed at its start, as measured (no scale, drift or bias).

    Its direction: the per-link compass fused with the turns, else the given
    heading, else (nothing orients it) the best hypothesis' rotation.
    """
    if compass is not None:
        fused = fused_directions(turns, compass, sigma, params.compass_walk, dt)
        theta, rel = float(fused[0]), np.r_[0.0, np.diff(fused)]
    else:
        theta = heading + float(turns[0]) if heading is not None else found.best.rotation
        rel = np.r_[0.0, turns[1:]]
    z = rigid_tracks(start, lengths, np.array([theta]), np.ones(1), rel[None, :])[0]
    return np.column_stack([z.real, z.imag])


def fit_in_pool(job: dict[str, Any]) -> dict[str, Any]:
    """Run one fit in a pool process, then return the allocator's free pages to the system.

    A fit's arrays leave their pages with the allocator, and the pool's
    processes live as long as the server: without the trim each fit would
    leave tens of megabytes resident (``python -m bench.trackfit`` runs fits
    of the same sizes).
    """
    try:
        return run_fit(job)
    finally:
        trim_allocator()


def run_fit(
    job: dict[str, Any],
    search: TrackSearchParams | None = None,
    verdict_params: VerdictParams | None = None,
) -> dict[str, Any]:
    """Fit one track; return status, points, score, what the fit knows, time (never raises).

    ``search`` and ``verdict_params`` replace the fitter's default constants
    (an evaluation studying them); the request's own overrides and the job's
    time limit apply on top. A fit the evidence does not single out is
    answered with the uploaded track placed at its start (``fitted`` false).
    """
    started = time.perf_counter()
    try:
        plan = _plan(job["site_id"], job["floor_id"], job["version"], job["floor_doc"], job["cell"])
        request = job["request"]
        segments = request["segments"]
        defaults = search or TrackSearchParams()
        params = replace(
            defaults,
            fit=replace(
                defaults.fit,
                grid=request.get("grid") or defaults.fit.grid,
                scales=tuple(request.get("scales") or defaults.fit.scales),
                turns=tuple(request.get("turns") or defaults.fit.turns),
                time_limit_s=job["time_limit_s"],
            ),
        )
        given = request.get("heading")
        # API heading: degrees clockwise from +y; engine direction: radians CCW from +x
        heading = None if given is None else math.radians(90.0 - given)
        times = np.array([request["t0"], *(s["t"] for s in segments)], dtype=float)
        seconds = (times - times[0]) / 1000.0
        anchors = _anchors(job, segments, params.fit.anchor_sigma)
        compass = _compass(segments)
        sigma = math.radians(request.get("heading_sigma_deg") or DEFAULT_HEADING_SIGMA_DEG)
        start = np.array([request["start"]["x"], request["start"]["y"]])
        lengths = np.array([s["length"] for s in segments])
        turns = np.array([s["turn"] for s in segments])
        found = search_track(
            plan,
            start,
            lengths,
            turns,
            heading=heading,
            times=seconds,
            anchors=anchors,
            compass=compass,
            compass_sigma=sigma,
            params=params,
        )
        verdict = judge(
            found,
            lengths,
            oriented=heading is not None or compass is not None,
            params=verdict_params or VerdictParams(),
        )
        placed = placed_track(
            found,
            start,
            lengths,
            turns,
            heading=heading,
            compass=compass,
            sigma=sigma,
            dt=durations(lengths, seconds, params.walking_speed),
            params=params,
        )
    except Exception as exc:  # a fit that cannot run must still finish as failed
        return {
            "status": "failed",
            "error": f"{type(exc).__name__}: {exc}",
            "elapsed_ms": (time.perf_counter() - started) * 1000,
        }
    return _answer(request, params, found, verdict, placed, anchors, started)


def _answer(
    request: dict[str, Any],
    params: TrackSearchParams,
    found: TrackSearch,
    verdict: Verdict,
    placed: np.ndarray,
    anchors: AnchorCosts | None,
    started: float,
) -> dict[str, Any]:
    """Return the stored result of a search: its points (the fit or the placed upload) and
    what the fit knows of itself."""
    segments = request["segments"]
    t_points = [request["t0"], *(s["t"] for s in segments)]
    best, runner_up = found.best, found.runner_up
    # the radius of the last point: the grid, the ends of as-good fits, an ambiguous
    # runner-up's end (either may be the walker), and the calibrated radius
    accuracy = max(params.fit.grid / 2, float(verdict.radius[-1]))
    if verdict.fitted:
        accuracy = max(accuracy, best.fit.spread)
    if found.ambiguous and runner_up is not None:
        accuracy = max(accuracy, float(np.hypot(*(runner_up.fit.points[-1] - best.fit.points[-1]))))
    done = not best.fit.failed
    xy = best.fit.points if verdict.fitted or not done else placed
    radius = verdict.radius[: len(xy)]
    candidates = [_candidate(best, None)]
    if runner_up is not None:
        shown = _points(t_points, runner_up.fit.points) if found.ambiguous else None
        candidates.append(_candidate(runner_up, shown))
    return {
        "status": "failed" if best.fit.failed else "done",
        "error": best.fit.failed,
        "points": _points(t_points, xy, radius),
        "score": best.score,
        "elapsed_ms": (time.perf_counter() - started) * 1000,
        "grid": params.fit.grid,
        "rotation": _heading_deg(best.rotation),
        "scale": round(best.scale, 3),
        "drift": round(math.degrees(best.drift), 3),
        "relaxed": best.fit.relaxed.astype(int).tolist(),
        "spread": round(best.fit.spread, 3),
        "accuracy": round(accuracy, 3),
        "anchors": len(anchors) if anchors is not None else 0,
        "ambiguous": found.ambiguous,
        "candidates": candidates,
        "fitted": verdict.fitted and done,
        "reason": verdict.reason if done else best.fit.failed,
        "margin": round(verdict.margin, 4) if math.isfinite(verdict.margin) else None,
        "bias": None if found.bias is None else round(-math.degrees(found.bias), 2),
    }
