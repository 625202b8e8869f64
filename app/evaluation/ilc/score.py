"""Estimates scored against a walk's waypoints, and pooled into one row per method.

Each estimate is compared with the waypoints interpolated at its time, only
inside the waypoints' span. Horizontal errors count only where the estimated
floor is right; the floor error is the share of estimates on a wrong floor;
the heading error is against the direction of the waypoint segment being
walked, on segments where the walker moves; "in acc." is the share of the
right-floor errors within the 68% accuracy radius each estimate reported
(68% when the radius is honest).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import spearmanr

from app.engine.pdr_fit import wrap_deg
from app.engine.samples import Estimate
from app.evaluation.metrics import truth_at

MIN_HEADING_SEGMENT_M = 1.0
"""Waypoint segments shorter than this have no meaningful direction."""

MIN_HEADING_SPEED_MPS = 0.3
"""Below this mean speed on a segment the walker is standing, not walking a direction."""


@dataclass(frozen=True)
class WalkScore:
    """One method's estimates on one walk, scored against the waypoints.

    Arrays cover the estimates inside the waypoints' span: ``floor_ok``
    whether the floor is right, ``error`` the horizontal error (m, NaN on a
    wrong floor), ``heading_error`` the absolute heading error (deg, NaN
    where the estimate has no heading or the walker does not move a direction),
    ``accuracy`` the 68% radius (m) each estimate reported.
    """

    floor_ok: np.ndarray
    error: np.ndarray
    heading_error: np.ndarray
    accuracy: np.ndarray


def path_direction(waypoints: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Return the direction (deg clockwise from +y) of the waypoint segment walked at ``t``.

    NaN outside the span, on segments shorter than ``MIN_HEADING_SEGMENT_M``
    or slower than ``MIN_HEADING_SPEED_MPS`` (standing).
    """
    t = np.asarray(t, dtype=float)
    wt, xy = waypoints[:, 0], waypoints[:, 1:3]
    out = np.full(t.shape, np.nan)
    if wt.size < 2:
        return out
    seg = np.clip(np.searchsorted(wt, t, side="right") - 1, 0, wt.size - 2)
    d = xy[seg + 1] - xy[seg]
    length = np.hypot(d[:, 0], d[:, 1])
    dt_s = (wt[seg + 1] - wt[seg]) / 1000.0
    with np.errstate(divide="ignore", invalid="ignore"):
        moving = (length >= MIN_HEADING_SEGMENT_M) & (length / dt_s >= MIN_HEADING_SPEED_MPS)
    ok = moving & (t >= wt[0]) & (t <= wt[-1])
    # φ = atan2(Δx, Δy), clockwise from +y
    out[ok] = np.mod(np.degrees(np.arctan2(d[ok, 0], d[ok, 1])), 360.0)
    return out


def estimates_from_positions(
    positions: Sequence[dict[str, Any]], floors: Sequence[str]
) -> list[Estimate]:
    """Return the API's position messages as estimates, floors numbered as in ``floors``
    (-1 for any other)."""
    index = {name: i for i, name in enumerate(floors)}

    def num(v: float | None) -> float:
        return float("nan") if v is None else float(v)

    return [
        Estimate(
            t=int(p["t"]),
            x=float(p["x"]),
            y=float(p["y"]),
            z=num(p.get("z")),
            floor=index.get(p["floor_id"], -1),
            heading=num(p.get("heading")),
            accuracy=num(p.get("accuracy")),
            speed=num(p.get("speed")),
            method=str(p.get("method")),
            smoothed=bool(p.get("smoothed")),
        )
        for p in positions
    ]


def score_walk(waypoints: np.ndarray, floor: int, estimates: Sequence[Estimate]) -> WalkScore:
    """Score a walk's estimates against its waypoints (m, 3: t, x, y) on floor index ``floor``."""
    if not estimates:
        empty = np.zeros(0)
        return WalkScore(np.zeros(0, bool), empty, empty, empty)
    t = np.array([e.t for e in estimates], dtype=np.int64)
    xy = np.array([[e.x, e.y] for e in estimates], dtype=float)
    est_floor = np.array([e.floor for e in estimates])
    heading = np.array([e.heading for e in estimates], dtype=float)
    accuracy = np.array([e.accuracy for e in estimates], dtype=float)
    true_xy, inside = truth_at(waypoints, t)
    floor_ok = est_floor[inside] == floor
    err = np.hypot(*(xy[inside] - true_xy[inside]).T)
    err = np.where(floor_ok, err, np.nan)
    direction = path_direction(waypoints, t[inside])
    heading_err = np.abs(wrap_deg(heading[inside] - direction))
    return WalkScore(floor_ok, err, heading_err, accuracy[inside])


@dataclass(frozen=True)
class Row:
    """One table row: a method's figures pooled over the evaluated walks."""

    method: str
    n: int
    mean: float
    p50: float
    p75: float
    p95: float
    floor_error: float
    heading_error: float
    n_heading: int
    in_accuracy: float
    radius_rank: float
    cpu_per_update_s: float
    walks: int
    walks_off_floor: int = 0


def radius_rank(error: np.ndarray, radius: np.ndarray) -> float:
    """Return Spearman's correlation of radius and error: does a larger radius mean a larger
    error? NaN with fewer than three estimates or a constant radius."""
    finite = np.isfinite(radius)
    error, radius = error[finite], radius[finite]
    if error.size < 3 or np.ptp(radius) == 0:
        return float("nan")
    return float(spearmanr(radius, error).statistic)


def summarise(method: str, scores: Sequence[WalkScore], cpu_s: float, updates: int) -> Row:
    """Pool walk scores into a row: errors on the right floor only, shares over all estimates."""
    ok = np.concatenate([s.floor_ok for s in scores]) if scores else np.zeros(0, bool)
    err = np.concatenate([s.error for s in scores]) if scores else np.zeros(0)
    hdg = np.concatenate([s.heading_error for s in scores]) if scores else np.zeros(0)
    acc = np.concatenate([s.accuracy for s in scores]) if scores else np.zeros(0)
    right = err[ok]
    # an honest 68% radius holds 68% of the errors on the right floor (of those with one)
    radius = acc[ok]
    within = right[np.isfinite(radius)] <= radius[np.isfinite(radius)]
    hdg = hdg[np.isfinite(hdg)]

    def pct(q: float) -> float:
        return float(np.percentile(right, q)) if right.size else float("nan")

    return Row(
        method=method,
        n=int(ok.size),
        mean=float(right.mean()) if right.size else float("nan"),
        p50=pct(50),
        p75=pct(75),
        p95=pct(95),
        floor_error=float(1.0 - ok.mean()) if ok.size else float("nan"),
        heading_error=float(hdg.mean()) if hdg.size else float("nan"),
        n_heading=int(hdg.size),
        in_accuracy=float(within.mean()) if within.size else float("nan"),
        radius_rank=radius_rank(right, acc[ok]),
        cpu_per_update_s=cpu_s / updates if updates else float("nan"),
        walks=len(scores),
        walks_off_floor=sum(s.floor_ok.size > 0 and s.floor_ok.mean() < 0.5 for s in scores),
    )
