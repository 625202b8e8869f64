"""Measure pedestrian dead reckoning on the ILC site1 walks against their surveyed waypoints.

Train walks (``walk_split``) calibrate Weinberg's K and the site's heading
offset; test walks are measured with both applied. Per walk: the ratio of
the summed step lengths to the waypoint polyline length between the first and
last waypoint. Per waypoint segment of at least ``min_segment_m``: the
circular mean heading of the steps taken on it minus the segment's direction.

Run ``python -m app.evaluation.pdr_eval`` (about a minute on one core).
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.datasets import data_dir
from app.datasets.ilc import imu_samples as walk_imu
from app.datasets.ilc import read_walk, site_walks
from app.engine.pdr import PdrParams, Steps, detect_steps
from app.evaluation.split import walk_split

MIN_SEGMENT_M = 3.0


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
    """Wrap angles (degrees) into [-180, 180)."""
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


def run_walks(
    walks: Iterable[tuple[str, Path]], params: PdrParams, *, rotation_vector: bool = True
) -> list[WalkPdr]:
    """Run PDR on each (floor, path) walk with at least two waypoints.

    Without ``rotation_vector`` the rotation vector is withheld, so headings
    come from the gyro + magnetometer complementary filter.
    """
    out = []
    for floor, path in walks:
        walk = read_walk(path, floor)
        if walk.waypoints.shape[0] < 2 or walk.acc.shape[0] == 0:
            continue
        imu = walk_imu(walk)
        if not rotation_vector:
            imu.rot = np.full_like(imu.rot, np.nan)
        steps = detect_steps(imu, params)
        out.append(walk_pdr(walk.walk_id, floor, walk.waypoints, steps))
    return out


def calibrate_k(results: list[WalkPdr]) -> float:
    """Return Weinberg's K fitting total step length to total walked distance."""
    # K = Σ D_w / Σ_w Σ_steps (a_max - a_min)^(1/4)
    return sum(r.distance for r in results) / sum(r.stride_sum for r in results)


def heading_offset(results: list[WalkPdr]) -> float:
    """Return the offset (degrees) to add to PDR headings: minus their mean segment error."""
    return -circular_mean(np.concatenate([r.segment_error for r in results]))


@dataclass(frozen=True)
class PdrReport:
    """Figures measured on the test walks with K and heading offset from the train walks."""

    k: float
    offset_deg: float
    n_train: int
    n_test: int
    ratio: np.ndarray
    heading_error_raw: np.ndarray
    heading_error: np.ndarray
    cadence_hz: np.ndarray


def evaluate(
    walks: list[tuple[str, Path]],
    params: PdrParams,
    test_fraction: float = 0.2,
    *,
    rotation_vector: bool = True,
) -> PdrReport:
    """Calibrate on the train walks, measure on the test walks."""
    _, test_ids = walk_split([p.name.split(".")[0] for _, p in walks], test_fraction)
    test_set = set(test_ids)
    results = run_walks(walks, params, rotation_vector=rotation_vector)
    train = [r for r in results if r.walk_id not in test_set]
    test = [r for r in results if r.walk_id in test_set]
    k = calibrate_k(train)
    offset = heading_offset(train)
    # ratio_w = K Σ swing^(1/4) / D_w
    ratio = np.array([k * r.stride_sum / r.distance for r in test if r.distance > 0])
    raw = np.concatenate([r.segment_error for r in test])
    return PdrReport(
        k=k,
        offset_deg=offset,
        n_train=len(train),
        n_test=len(test),
        ratio=ratio,
        heading_error_raw=raw,
        heading_error=wrap_deg(raw + offset),
        cadence_hz=np.array([r.n_steps / r.duration_s for r in test if r.duration_s > 0]),
    )


def format_report(rep: PdrReport) -> str:
    """Render the report as a plain-text table."""
    q = np.percentile
    abs_raw, abs_cor = np.abs(rep.heading_error_raw), np.abs(rep.heading_error)
    lines = [
        f"walks: {rep.n_train} train, {rep.n_test} test",
        f"Weinberg K (train)                 {rep.k:.4f}",
        f"heading offset to add (train, deg) {rep.offset_deg:+.2f}",
        "",
        f"{'test metric':40s} {'median':>8s} {'mean':>8s} {'p25':>8s} {'p75':>8s}",
        f"{'step length sum / path length':40s} {np.median(rep.ratio):8.3f} "
        f"{rep.ratio.mean():8.3f} {q(rep.ratio, 25):8.3f} {q(rep.ratio, 75):8.3f}",
        f"{'cadence (steps/s)':40s} {np.median(rep.cadence_hz):8.3f} "
        f"{rep.cadence_hz.mean():8.3f} {q(rep.cadence_hz, 25):8.3f} {q(rep.cadence_hz, 75):8.3f}",
        f"{'|heading error|, no offset (deg)':40s} {np.median(abs_raw):8.2f} "
        f"{abs_raw.mean():8.2f} {q(abs_raw, 25):8.2f} {q(abs_raw, 75):8.2f}",
        f"{'|heading error|, train offset (deg)':40s} {np.median(abs_cor):8.2f} "
        f"{abs_cor.mean():8.2f} {q(abs_cor, 25):8.2f} {q(abs_cor, 75):8.2f}",
        f"segments >= {MIN_SEGMENT_M:g} m: {rep.heading_error.size}",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Measure PDR on an ILC site and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", type=Path, default=data_dir() / "ilc" / "site1")
    parser.add_argument("--test-fraction", type=float, default=0.2)
    parser.add_argument(
        "--no-rotation-vector",
        action="store_true",
        help="withhold the rotation vector: headings from gyro + magnetometer",
    )
    args = parser.parse_args(argv)
    report = evaluate(
        site_walks(args.site),
        PdrParams(),
        args.test_fraction,
        rotation_vector=not args.no_rotation_vector,
    )
    print(format_report(report))


if __name__ == "__main__":
    main()
