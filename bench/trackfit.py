"""Track-fit benchmark: time of ``search_track`` by track length and DP grid on a real floor.

Uses the site1 floor with the largest walkable area, rasterised at the
service's 0.25 m. Tracks are synthetic: a walker steps along the corridors of
the plan (straight on, turning where a wall comes up), then the links are
perturbed as a phone would (a walker scale, per-link length factor, turn
noise and a drifting heading) and the initial heading is withheld, so every
run includes the rotation, scale and drift search. Prints, per track length
and grid, the DP cell the fitter used (the grid, or less for links shorter
than it), the hypotheses screened, the median time over a few runs, the
largest |S_i|, whether the fit completed, and the mean distance between
fitted and true points.

    python bench/trackfit.py --links 50 171 500 --grids 2 1 0.5 --runs 3
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.datasets import data_dir  # noqa: E402
from app.datasets.ilc import floor_map_geojson  # noqa: E402
from app.engine.plan import FloorPlan  # noqa: E402
from app.engine.trackfit.fit import TrackFitParams  # noqa: E402
from app.engine.trackfit.search import TrackSearchParams, search_track  # noqa: E402
from app.geometry.floormap import FloorMap, parse_floor_map  # noqa: E402
from app.geometry.raster import floor_plan  # noqa: E402


def largest_floor(site_dir: Path) -> tuple[str, FloorMap]:
    """Return the name and map of the floor with the largest walkable area."""
    maps = {
        d.name: parse_floor_map(floor_map_geojson(d))
        for d in sorted(site_dir.iterdir())
        if (d / "geojson_map.json").exists()
    }
    name = max(maps, key=lambda k: maps[k].walkable.area)
    return name, maps[name]


def free_run(plan: FloorPlan, pos: np.ndarray, psi: np.ndarray, reach: float) -> np.ndarray:
    """Return how far (m, up to ``reach``) one can walk from ``pos`` in each direction ``psi``."""
    d = np.arange(1, int(reach / 0.25) + 1) * 0.25
    pts = pos + d[:, None, None] * np.stack([np.cos(psi), np.sin(psi)], axis=-1)[None]
    blocked = ~plan.is_free(pts)
    return np.where(blocked.any(axis=0), d[np.argmax(blocked, axis=0)] - 0.25, reach)


def corridor_walk(
    plan: FloorPlan, n: int, step: float, rng: np.random.Generator, margin: float = 0.8
) -> np.ndarray:
    """Return n + 1 points of a walk along the plan's corridors, shape (n + 1, 2).

    The walker goes straight with a little heading jitter while there is room
    ahead; when a wall comes within a step plus ``margin``, or at random now
    and then, it turns towards the direction with the longest free run
    (right angles and diagonals first, turning back only when cornered).
    """
    starts = plan.sample_free(4000, rng)
    pos = starts[np.argmax(plan.clearance_at(starts) >= 2.0)]
    psi = rng.uniform(-np.pi, np.pi)
    out = [pos]
    turns = np.radians([90.0, -90.0, 45.0, -45.0, 135.0, -135.0, 180.0])
    while len(out) <= n:
        psi += rng.normal(0.0, 0.03)
        ahead = free_run(plan, pos, np.array([psi]), step + margin)[0]
        if ahead < step + margin or rng.random() < 0.02:
            options = psi + turns + rng.normal(0.0, 0.05, size=turns.size)
            run = free_run(plan, pos, options, 15.0)
            # Prefer the longest run; a turn back only when nothing else is open.
            run[-1] *= 0.2
            psi = options[int(np.argmax(run))]
        nxt = pos + step * np.array([np.cos(psi), np.sin(psi)])
        if plan.segment_free(pos[None], nxt[None])[0]:
            pos = nxt
        out.append(pos)
    return np.array(out)


def as_links(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return link lengths, turns (first one 0) and directions (rad) of a polyline."""
    d = np.diff(points, axis=0)
    length = np.hypot(d[:, 0], d[:, 1])
    direction = np.arctan2(d[:, 1], d[:, 0])
    # turn_i = wrap(θ_i - θ_{i-1})
    turn = np.r_[0.0, np.angle(np.exp(1j * np.diff(direction)))]
    return length, turn, direction


def run(args: argparse.Namespace) -> None:
    """Time every (track length, grid) pair and print the table."""
    site = data_dir() / "ilc" / "site1"
    name, fmap = largest_floor(site)
    plan = floor_plan(fmap, cell=args.raster)
    print(
        f"floor {name}: walkable {fmap.walkable.area:.0f} m², raster {args.raster} m "
        f"{plan.shape[1]}×{plan.shape[0]}, link ≈ {args.step} m, runs {args.runs}"
    )
    rng = np.random.default_rng(args.seed)
    header = (
        f"{'links':>6} {'grid m':>7} {'cell m':>7} {'screened':>8} {'median s':>9} "
        f"{'max |S_i|':>10} {'fit':>5} {'err m':>7}"
    )
    print(header)
    print("-" * len(header))
    for n in args.links:
        truth = corridor_walk(plan, n, args.step, rng)
        length, turn, _ = as_links(truth)
        # Phone-like errors at a step every 0.6 s: the walker's steps 6 % long,
        # each off by up to 5 %; the heading sways by 2° about a direction
        # that drifts by 0.1°/s (a gyro bias), so turns carry the sway's changes.
        dt = 0.6
        raw_len = 1.06 * length * rng.uniform(0.95, 1.05, size=n)
        error = np.radians(0.1) * dt * np.arange(n) + rng.normal(0.0, np.radians(2.0), size=n)
        raw_turn = turn + np.r_[0.0, np.diff(error)]
        times = dt * np.arange(n + 1)
        for grid in args.grids:
            params = TrackSearchParams(fit=TrackFitParams(grid=grid, time_limit_s=args.time_limit))
            seconds = []
            for _ in range(args.runs):
                t0 = time.perf_counter()
                found = search_track(plan, truth[0], raw_len, raw_turn, times=times, params=params)
                seconds.append(time.perf_counter() - t0)
            fit = found.best.fit
            ok = fit.failed is None
            err = np.linalg.norm(fit.points - truth[: fit.points.shape[0]], axis=1).mean()
            print(
                f"{n:>6} {grid:>7.2f} {fit.cell:>7.2f} {found.screened:>8} "
                f"{np.median(seconds):>9.3f} {fit.alive.max():>10} "
                f"{'yes' if ok else 'no':>5} {err:>7.2f}"
            )


def main() -> None:
    """Parse the options and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--links", type=int, nargs="+", default=[50, 171, 500])
    parser.add_argument("--grids", type=float, nargs="+", default=[2.0, 1.0, 0.5])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--step", type=float, default=0.7, help="true link length (m)")
    parser.add_argument("--raster", type=float, default=0.25, help="plan raster cell (m)")
    parser.add_argument("--time-limit", type=float, default=120.0)
    parser.add_argument("--seed", type=int, default=4)
    run(parser.parse_args())


if __name__ == "__main__":
    main()
