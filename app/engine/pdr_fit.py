"""Pedestrian dead reckoning measured against surveyed waypoints, and its constants fitted.

A walk's steps are compared with its waypoint polyline: the summed step
swing against the walked distance (which fits Weinberg's K) and, per long
enough segment, the mean step heading against the segment's direction (which
fits the heading offset, the rotation of the site frame against magnetic
north). A radio-map build fits a site's constants from its survey walks this
way, and the evaluations from their training walks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from app.engine.pdr import PdrParams, Steps, detect_steps
from app.engine.samples import ImuSamples

MIN_SEGMENT_M = 3.0
"""Waypoint segments shorter than this give no heading to compare with."""


@dataclass(frozen=True)
class WalkPdr:
    """PDR of one walk reduced to what the metrics need.

    ``distance`` is the waypoint polyline length (m); ``stride_sum`` the sum of
    swing^(1/4) of the steps between the first and last waypoint (Weinberg
    length is K times it); ``n_steps`` those steps; ``duration_s`` the time
    from first to last waypoint; ``segment_error`` the signed heading error
    (degrees, PDR minus truth, in [-180, 180)) of each long enough segment.
    """

    walk_id: str
    floor: str
    distance: float
    stride_sum: float
    n_steps: int
    duration_s: float
    segment_error: np.ndarray


def wrap_deg(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles (degrees) into [-180, 180), so heading differences compare across north."""
    # ((a + 180) mod 360) - 180
    return np.mod(np.asarray(a, dtype=float) + 180.0, 360.0) - 180.0


def circular_mean(deg: np.ndarray) -> float:
    """Return the circular mean of angles in degrees, in [-180, 180); NaN for none."""
    if deg.size == 0:
        return float("nan")
    r = np.radians(deg)
    # θ̄ = atan2(Σ sin θ, Σ cos θ)
    return float(wrap_deg(np.degrees(np.arctan2(np.sin(r).sum(), np.cos(r).sum()))))


def walk_pdr(
    walk_id: str,
    floor: str,
    waypoints: np.ndarray,
    steps: Steps,
    min_segment_m: float = MIN_SEGMENT_M,
) -> WalkPdr:
    """Compare one walk's steps with its waypoints (m, 3): t_ms, x, y."""
    t_wp, xy = waypoints[:, 0], waypoints[:, 1:]
    seg = np.diff(xy, axis=0)
    # d_i = |p_{i+1} - p_i|
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    # φ_i = atan2(Δx, Δy): clockwise from +y
    seg_dir = np.degrees(np.arctan2(seg[:, 0], seg[:, 1]))
    inside = (steps.t > t_wp[0]) & (steps.t <= t_wp[-1])
    errors = []
    for i in np.flatnonzero(seg_len >= min_segment_m):
        on = (steps.t > t_wp[i]) & (steps.t <= t_wp[i + 1]) & np.isfinite(steps.heading)
        if on.any():
            errors.append(wrap_deg(circular_mean(steps.heading[on]) - seg_dir[i]))
    return WalkPdr(
        walk_id=walk_id,
        floor=floor,
        distance=float(seg_len.sum()),
        # Σ (a_max - a_min)^(1/4)
        stride_sum=float(np.power(steps.swing[inside], 0.25).sum()),
        n_steps=int(inside.sum()),
        duration_s=float((t_wp[-1] - t_wp[0]) / 1000.0),
        segment_error=np.array(errors, dtype=float),
    )


def calibrate_k(results: Sequence[WalkPdr]) -> float:
    """Return Weinberg's K fitting total step length to total walked distance."""
    # K = Σ D_w / Σ_w Σ_steps (a_max - a_min)^(1/4)
    return sum(r.distance for r in results) / sum(r.stride_sum for r in results)


def heading_offset(results: Sequence[WalkPdr]) -> float:
    """Return the offset (degrees) to add to PDR headings: minus their mean segment error."""
    return -circular_mean(np.concatenate([r.segment_error for r in results]))


def fit_pdr_constants(walks: Sequence[WalkPdr], base: PdrParams) -> PdrParams:
    """Return ``base`` with Weinberg's K and the heading offset fitted on measured walks.

    The offset is a property of the building, K of the walkers' step scale:
    both are learned once per site from its survey walks. With no walked
    distance or no long segment, ``base``'s value is kept.
    """
    k = calibrate_k(walks) if sum(w.stride_sum for w in walks) > 0 else base.weinberg_k
    segments = [w.segment_error for w in walks]
    has_segments = any(e.size for e in segments)
    offset = heading_offset(walks) if has_segments else base.heading_offset_deg
    return replace(base, weinberg_k=k, heading_offset_deg=offset)


def measure_walk(
    walk_id: str, floor: str, waypoints: np.ndarray, imu: ImuSamples, params: PdrParams
) -> WalkPdr | None:
    """Detect a walk's steps and compare them with its waypoints; None without either."""
    if waypoints.shape[0] < 2 or len(imu) == 0:
        return None
    return walk_pdr(walk_id, floor, waypoints, detect_steps(imu, params))
