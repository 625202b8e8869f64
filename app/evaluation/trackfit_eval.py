"""Measure the track-to-plan fitter (seed 004) on the ILC site1 held-out walks.

For every test walk (``walk_split`` by walk id) the dead-reckoned track is
built from the walk's own IMU with the engine's PDR (steps with Weinberg
length and rotation-vector heading), starting at the first waypoint at its
time. The fitter then receives what a device in energy-saving mode would
upload: the start point and the track as links (length, turn), either one
link per step or steps merged into straight links between turns (Ramer–
Douglas–Peucker on the raw polyline). The initial heading is withheld, as in
the paper, or given as the PDR's.

Positions are compared with the surveyed waypoints at the waypoints' times
(the first waypoint, the given start, excluded). A fitted link is a scaled
and rotated copy of its raw chord, so the steps inside a merged link are
carried along by the same similarity before interpolating in time. A fit that
fails is scored with the raw track (what a server falls back to) and counted.

Run ``python -m app.evaluation.trackfit_eval [--plots DIR]``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.datasets import data_dir
from app.datasets.ilc import imu_samples, read_floor, read_walk, site_walks
from app.engine.pdr import detect_steps
from app.engine.plan import FloorPlan
from app.engine.trackfit.fit import TrackFitParams, fit_track
from app.evaluation.metrics import truth_at
from app.evaluation.plots import plan_figure
from app.evaluation.split import split_ids
from app.geometry.floormap import parse_floor_map
from app.geometry.raster import floor_plan

RASTER_CELL_M = 0.25
"""Raster of the plans: the service's default (``Settings.raster_cell``)."""

MERGE_TOLERANCE_M = 1.0
"""Steps are merged into one link while no step point strays further than
this from the link's chord (Ramer–Douglas–Peucker)."""

LINK_MODES = ("step", "merged")
HEADING_MODES = ("unknown", "known")


@dataclass(frozen=True)
class RawTrack:
    """A walk's dead-reckoned track from its first waypoint.

    ``t`` (n + 1,) int64 ms and ``xy`` (n + 1, 2) m: the start, then the end
    of each step taken after the first and up to the last waypoint.
    """

    t: np.ndarray
    xy: np.ndarray


@dataclass(frozen=True)
class WalkResult:
    """Errors (m) at the waypoints after the first, raw and fitted, of one walk and mode."""

    walk_id: str
    floor: str
    links: str
    heading: str
    n_links: int
    raw: np.ndarray
    fitted: np.ndarray
    failed: str | None
    seconds: float
    relaxed: int = 0
    """Links placed by the fitter's recovery ladder (no track survived them)."""
    spread: float = 0.0
    """How far apart (m) equally good fits end (``TrackFit.spread``)."""


def raw_track(
    walk_t: np.ndarray,
    step_t: np.ndarray,
    length: np.ndarray,
    heading_deg: np.ndarray,
    start: np.ndarray,
) -> RawTrack:
    """Dead-reckon steps (length m, heading degrees clockwise from +y) from ``start``.

    ``walk_t`` is (t_first, t_last) of the waypoints; steps outside are dropped.
    """
    keep = (step_t > walk_t[0]) & (step_t <= walk_t[1]) & np.isfinite(heading_deg)
    # θ = π/2 - ψ: counter-clockwise from +x
    theta = np.pi / 2 - np.radians(heading_deg[keep])
    steps = length[keep, None] * np.column_stack([np.cos(theta), np.sin(theta)])
    xy = np.vstack([start, start + np.cumsum(steps, axis=0)])
    return RawTrack(t=np.r_[walk_t[0], step_t[keep]].astype(np.int64), xy=xy)


def simplify(xy: np.ndarray, tolerance: float) -> np.ndarray:
    """Return the indices of the vertices Ramer–Douglas–Peucker keeps, first and last included."""
    keep = np.zeros(len(xy), dtype=bool)
    keep[[0, -1]] = True
    stack = [(0, len(xy) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        a, b = xy[i], xy[j]
        d = b - a
        p = xy[i + 1 : j] - a
        norm = np.hypot(d[0], d[1])
        # distance to the chord: |d × p| / |d|, or |p| when the chord is a point
        dist = np.abs(d[0] * p[:, 1] - d[1] * p[:, 0]) / norm if norm > 0 else np.hypot(*p.T)
        k = int(np.argmax(dist))
        if dist[k] > tolerance:
            m = i + 1 + k
            keep[m] = True
            stack += [(i, m), (m, j)]
    return np.flatnonzero(keep)


def as_links(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return lengths (m), turns (rad, first 0) and directions of a polyline's links."""
    d = np.diff(xy, axis=0)
    direction = np.arctan2(d[:, 1], d[:, 0])
    # turn_i = wrap(θ_i - θ_{i-1}) into [-π, π)
    turn = np.r_[0.0, np.mod(np.diff(direction) + np.pi, 2 * np.pi) - np.pi]
    return np.hypot(d[:, 0], d[:, 1]), turn, direction


def carry_steps(raw: np.ndarray, vertex: np.ndarray, fitted: np.ndarray) -> np.ndarray:
    """Move every raw point by the similarity that maps its link's raw chord to the fitted one.

    Parameters
    ----------
    raw : ndarray, shape (n + 1, 2)
        Raw step points.
    vertex : ndarray of int, shape (k + 1,)
        Indices into ``raw`` of the link ends, from 0 to n.
    fitted : ndarray, shape (k' + 1, 2)
        Fitted link ends, k' ≤ k (fewer when the fit stopped early).

    Returns
    -------
    ndarray, shape (m + 1, 2)
        Fitted step points up to ``vertex[k']``.
    """
    z_raw = raw[:, 0] + 1j * raw[:, 1]
    z_fit = fitted[:, 0] + 1j * fitted[:, 1]
    out = [z_fit[:1]]
    for i in range(len(fitted) - 1):
        a, b = vertex[i], vertex[i + 1]
        chord = z_raw[b] - z_raw[a]
        # z = (x_i - x_{i-1}) / (r_b - r_a): scale and rotation of the link
        z = (z_fit[i + 1] - z_fit[i]) / chord if abs(chord) > 0 else 1.0
        out.append(z_fit[i] + z * (z_raw[a + 1 : b + 1] - z_raw[a]))
    pts = np.concatenate(out)
    return np.column_stack([pts.real, pts.imag])


def position_at(t_points: np.ndarray, xy: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Interpolate a timed polyline at times ``t`` (held at its ends), shape (len(t), 2)."""
    return np.column_stack([np.interp(t, t_points, xy[:, 0]), np.interp(t, t_points, xy[:, 1])])


def fit_walk(
    plan: FloorPlan, raw: RawTrack, links: str, heading: str, params: TrackFitParams
) -> tuple[np.ndarray, np.ndarray, str | None, int, float, int, float]:
    """Fit one raw track: step points, times, failure, links, seconds, relaxed links, spread."""
    vertex = np.arange(len(raw.xy)) if links == "step" else simplify(raw.xy, MERGE_TOLERANCE_M)
    lengths, turns, direction = as_links(raw.xy[vertex])
    t0 = time.perf_counter()
    # A start on a blocked cell is the fitter's to snap (``snap_start``).
    fit = fit_track(
        plan,
        raw.xy[0],
        lengths,
        turns,
        heading=float(direction[0]) if heading == "known" and lengths.size else None,
        params=params,
    )
    seconds = time.perf_counter() - t0
    pts = carry_steps(raw.xy, vertex, fit.points)
    relaxed = int(np.count_nonzero(fit.relaxed))
    return pts, raw.t[: len(pts)], fit.failed, int(lengths.size), seconds, relaxed, fit.spread


def evaluate_walk(
    walk_id: str,
    floor: str,
    plan: FloorPlan,
    waypoints: np.ndarray,
    raw: RawTrack,
    params: TrackFitParams,
) -> tuple[list[WalkResult], dict[tuple[str, str], np.ndarray]]:
    """Fit one walk in every (links, heading) mode; return results and fitted step points."""
    t_eval = waypoints[1:, 0]
    truth, _ = truth_at(waypoints, t_eval)
    raw_err = np.linalg.norm(position_at(raw.t, raw.xy, t_eval) - truth, axis=1)
    results, tracks = [], {}
    for links in LINK_MODES:
        for heading in HEADING_MODES:
            pts, t_pts, failed, n_links, seconds, relaxed, spread = fit_walk(
                plan, raw, links, heading, params
            )
            tracks[(links, heading)] = pts
            fitted = raw.xy if failed else pts
            fit_t = raw.t if failed else t_pts
            err = np.linalg.norm(position_at(fit_t, fitted, t_eval) - truth, axis=1)
            results.append(
                WalkResult(
                    walk_id,
                    floor,
                    links,
                    heading,
                    n_links,
                    raw_err,
                    err,
                    failed,
                    seconds,
                    relaxed,
                    spread,
                )
            )
    return results, tracks


def plot_walk(
    path: Path,
    plan: FloorPlan,
    waypoints: np.ndarray,
    raw: RawTrack,
    fitted: np.ndarray,
    title: str,
) -> None:
    """Draw the plan, the true, raw and fitted tracks into a PNG file."""
    with plan_figure(path, plan, title, width_in=9.0) as ax:
        ax.plot(
            waypoints[:, 1], waypoints[:, 2], "o-", color="tab:green", ms=4, lw=2, label="truth"
        )
        ax.plot(raw.xy[:, 0], raw.xy[:, 1], "-", color="tab:red", lw=1, label="raw PDR")
        ax.plot(fitted[:, 0], fitted[:, 1], "-", color="tab:blue", lw=1.5, label="fitted")
        ax.plot(*raw.xy[0], "k*", ms=12)
        xmin, ymin, xmax, ymax = plan.bounds
        every = np.vstack([waypoints[:, 1:], raw.xy, fitted])
        lo, hi = every.min(axis=0) - 10.0, every.max(axis=0) + 10.0
        ax.set_xlim(max(lo[0], xmin), min(hi[0], xmax))
        ax.set_ylim(max(lo[1], ymin), min(hi[1], ymax))


def format_summary(results: list[WalkResult]) -> str:
    """Render per-mode figures over all test walks as a plain-text table."""
    lines = [
        f"{'links':<7} {'heading':<8} {'walks':>5} {'failed':>6} {'raw mean':>9} "
        f"{'fit mean':>9} {'raw med':>8} {'fit med':>8} {'ok: raw':>8} {'ok: fit':>8} "
        f"{'walk fit<raw':>12} {'s/fit med':>9} {'s/fit max':>9} {'relaxed':>7} "
        f"{'spread med':>10}"
    ]
    for links in LINK_MODES:
        for heading in HEADING_MODES:
            rs = [r for r in results if r.links == links and r.heading == heading]
            if not rs:
                continue
            raw = np.concatenate([r.raw for r in rs])
            fit = np.concatenate([r.fitted for r in rs])
            ok = [r for r in rs if r.failed is None]
            ok_raw = np.concatenate([r.raw for r in ok]) if ok else np.zeros(0)
            ok_fit = np.concatenate([r.fitted for r in ok]) if ok else np.zeros(0)
            better = sum(r.fitted.mean() < r.raw.mean() for r in rs)
            secs = np.array([r.seconds for r in rs])
            relaxed = sum(r.relaxed > 0 for r in rs)
            lines.append(
                f"{links:<7} {heading:<8} {len(rs):>5} {len(rs) - len(ok):>6} {raw.mean():>9.2f} "
                f"{fit.mean():>9.2f} {np.median(raw):>8.2f} {np.median(fit):>8.2f} "
                f"{ok_raw.mean() if ok else np.nan:>8.2f} {ok_fit.mean() if ok else np.nan:>8.2f} "
                f"{better:>5}/{len(rs):<6} {np.median(secs):>9.3f} {secs.max():>9.3f} "
                f"{relaxed:>7} {np.median([r.spread for r in rs]):>10.2f}"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Fit every held-out site1 walk and print per-walk and overall errors."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", type=Path, default=data_dir() / "ilc" / "site1")
    parser.add_argument("--test-fraction", type=float, default=0.2)
    parser.add_argument(
        "--split",
        choices=("test", "validation"),
        default="test",
        help="held-out test walks, or a validation split carved from the training walks "
        "(for tuning; never tune on test)",
    )
    parser.add_argument("--validation-fraction", type=float, default=0.2)
    parser.add_argument("--grid", type=float, default=TrackFitParams().grid)
    parser.add_argument("--cell-per-link", type=float, default=TrackFitParams().cell_per_link)
    parser.add_argument("--time-limit", type=float, default=30.0)
    parser.add_argument("--plots", type=Path, default=None, help="write one PNG per walk here")
    parser.add_argument("--quiet", action="store_true", help="no per-walk lines")
    args = parser.parse_args(argv)

    params = TrackFitParams(
        grid=args.grid,
        cell_per_link=args.cell_per_link,
        time_limit_s=args.time_limit,
    )
    walks = site_walks(args.site)
    _, validation_ids, test_ids = split_ids(
        [p.name.split(".")[0] for _, p in walks], args.test_fraction, args.validation_fraction
    )
    test = set(validation_ids if args.split == "validation" else test_ids)
    plans: dict[str, FloorPlan] = {}
    if args.plots:
        args.plots.mkdir(parents=True, exist_ok=True)
    results: list[WalkResult] = []
    print(
        f"site {args.site.name}: {len(test)} {args.split} walks, grid {args.grid} m, "
        f"cell per link {args.cell_per_link}, raster "
        f"{RASTER_CELL_M} m, merge tolerance {MERGE_TOLERANCE_M} m"
    )
    if not args.quiet:
        print(
            f"{'walk':<26} {'floor':<5} {'links':<7} {'heading':<8} {'n':>4} {'raw':>7} "
            f"{'fitted':>7} {'s':>6} {'relax':>5}  failed"
        )
    for floor, path in walks:
        walk_id = path.name.split(".")[0]
        if walk_id not in test:
            continue
        walk = read_walk(path, floor)
        if walk.waypoints.shape[0] < 2 or walk.acc.shape[0] == 0:
            continue
        if floor not in plans:
            fmap = parse_floor_map(read_floor(args.site / floor).geojson)
            plans[floor] = floor_plan(fmap, cell=RASTER_CELL_M)
        plan = plans[floor]
        steps = detect_steps(imu_samples(walk))
        wp = walk.waypoints
        raw = raw_track(wp[[0, -1], 0], steps.t, steps.length, steps.heading, wp[0, 1:])
        if len(raw.xy) < 2:
            continue
        walk_results, tracks = evaluate_walk(walk_id, floor, plan, wp, raw, params)
        results += walk_results
        if not args.quiet:
            for r in walk_results:
                print(
                    f"{r.walk_id:<26} {r.floor:<5} {r.links:<7} {r.heading:<8} {r.n_links:>4} "
                    f"{r.raw.mean():>7.2f} {r.fitted.mean():>7.2f} {r.seconds:>6.2f} "
                    f"{r.relaxed:>5}  "
                    f"{r.failed or ''}"
                )
        if args.plots:
            main_fit = next(
                r for r in walk_results if (r.links, r.heading) == ("merged", "unknown")
            )
            plot_walk(
                args.plots / f"{floor}_{walk_id}.png",
                plan,
                wp,
                raw,
                tracks[("merged", "unknown")],
                f"{floor} {walk_id}\nraw {main_fit.raw.mean():.2f} m, fitted (merged links, "
                f"heading unknown) {main_fit.fitted.mean():.2f} m"
                + (f" — {main_fit.failed}" if main_fit.failed else ""),
            )
    print()
    print("errors (m) at the waypoints after the first; failed fits scored with the raw track;")
    print("relaxed: walks with a link placed by the fitter's recovery ladder; spread: how far")
    print("apart (m) the fits scoring within one Φ step of the best end (ambiguity)")
    print(format_summary(results))


if __name__ == "__main__":
    main()
