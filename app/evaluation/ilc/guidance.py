"""Does the survey guidance tell where positioning is bad? Checked on ILC site1's walks.

The surveyed walks are cross-validated as a build does (walk-level folds,
WKNN with the k of lowest held-out error) and smoothed into each floor's
expected-error grid (``app.engine.survey_guidance``). Then the held-out walks,
which neither the folds nor the grid saw, are located scan by scan by WKNN on
maps built from every surveyed walk, and each scan's error (a wrong floor as
``wrong_floor_m``) is set against the grid's value at its true position: if
the guidance is right, scans where it expects large errors err more, and
scans on unsurveyed cells most. Run ``locus eval ilc-guidance``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

from app.datasets.ilc import Walk, fresh_wifi, read_floor
from app.engine.crossval import HeldOut, cross_validate, wknn_scans
from app.engine.radiomap import RadioMapParams, Survey
from app.engine.survey_guidance import GuidanceGrid, GuidanceParams, scan_errors, site_guidance
from app.engine.tuning import WKNN_K_CANDIDATES
from app.engine.wknn import Fingerprints, WknnParams
from app.evaluation.ilc.learn import radio_maps
from app.evaluation.ilc.recordings import (
    MAX_WIFI_AGE_MS,
    PLAN_CELL_M,
    SiteRecordings,
    survey_of,
)
from app.evaluation.ilc.server import add_site_arguments, split_site
from app.evaluation.markdown import markdown_table
from app.geometry.floormap import parse_floor_map
from app.geometry.raster import floor_plan

BINS_M = (0.0, 4.0, 8.0, 16.0, np.inf)
"""Edges of the expected-error classes the table compares (m)."""

COLUMNS = (
    "expected error",
    "walkable area",
    "validation scans",
    "mean expected m",
    "mean actual m",
    "p50 actual m",
    "p90 actual m",
    "wrong floor",
)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Parse the options of ``locus eval ilc-guidance``."""
    parser = argparse.ArgumentParser(
        prog="locus eval ilc-guidance", description=__doc__.splitlines()[0] if __doc__ else None
    )
    add_site_arguments(parser, "score the guidance on it instead of the test walks")
    parser.add_argument("--folds", type=int, default=5, help="walk-level folds of the build")
    parser.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    return parser.parse_args(argv)


def recordings(
    site_dir: Path, floors: list[str], surveyed: list[Walk], held: list[Walk]
) -> SiteRecordings:
    """Return the floors' plans and the walks, transmitters as the surveyed walks heard them."""
    plans = tuple(
        floor_plan(parse_floor_map(read_floor(site_dir / f).geojson), cell=PLAN_CELL_M)
        for f in floors
    )
    heard = {b for w in surveyed for b in fresh_wifi(w.wifi, MAX_WIFI_AGE_MS).bssid.tolist()}
    walks = surveyed + held
    return SiteRecordings(tuple(floors), plans, tuple(walks), tuple(sorted(heard)))


def expected_at(
    grids: dict[int, GuidanceGrid], floor: np.ndarray, xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Return the expected error at each position (NaN unsurveyed) and whether the position
    falls on a walkable cell of its floor's grid."""
    value = np.full(floor.size, np.nan)
    on_grid = np.zeros(floor.size, dtype=bool)
    for f, grid in grids.items():
        rows = np.flatnonzero(floor == f)
        ij = np.floor((xy[rows] - grid.origin) / grid.cell).astype(np.int64)
        ny, nx = grid.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] >= 0) & (ij[:, 1] < ny)
        r, c = np.clip(ij[:, 1], 0, ny - 1), np.clip(ij[:, 0], 0, nx - 1)
        walkable = inside & grid.walkable[r, c]
        on_grid[rows] = walkable
        value[rows] = np.where(walkable, grid.error_m[r, c], np.nan)
    return value, on_grid


def other_fold_distance(survey: Survey, held: HeldOut) -> np.ndarray:
    """Return each held-out scan's distance (m) to the nearest scan of the other folds on its
    floor (∞ without one): how far the maps it was located on reached towards it."""
    fold = survey.scan_walk % held.folds
    floor = survey.scan_floor
    out = np.full(held.scan.size, np.inf)
    for f in np.unique(fold[held.scan]):
        for level in np.unique(floor[held.scan]):
            train = np.flatnonzero((fold != f) & (floor == level))
            rows = np.flatnonzero((fold[held.scan] == f) & (floor[held.scan] == level))
            if train.size and rows.size:
                out[rows], _ = cKDTree(survey.scan_xy[train]).query(survey.scan_xy[held.scan[rows]])
    return out


def _row(label: str, area: float, expected: np.ndarray, actual: np.ndarray, wrong: np.ndarray):
    n = actual.size
    if n == 0:
        return [label, f"{100 * area:.1f}%", "0", "—", "—", "—", "—", "—"]
    mean_expected = f"{np.mean(expected):.2f}" if np.isfinite(expected).all() else "—"
    return [
        label,
        f"{100 * area:.1f}%",
        str(n),
        mean_expected,
        f"{np.mean(actual):.2f}",
        f"{np.median(actual):.2f}",
        f"{np.percentile(actual, 90):.2f}",
        f"{100 * np.mean(wrong):.1f}%",
    ]


def main(argv: Sequence[str] | None = None) -> None:
    """Build the guidance from the surveyed walks, score it on the held-out walks, print."""
    args = parse_args(argv)
    site_dir, floors, surveyed, held = split_site(args)
    site = recordings(site_dir, floors, surveyed, held)
    survey = survey_of(site, [w.walk_id for w in surveyed])
    located = survey_of(site, [w.walk_id for w in held])
    plans = dict(enumerate(site.plans))
    radio, wknn, params = RadioMapParams(), WknnParams(), GuidanceParams()
    cv = cross_validate(survey, plans, radio, wknn, folds=args.folds, ks=WKNN_K_CANDIDATES)
    if cv is None:
        raise SystemExit("fewer than two surveyed walks: nothing to hold out")
    k = cv.best_k()
    grids = site_guidance(survey, cv.by_k[k], plans, params)
    maps = tuple(m for m in radio_maps(site, survey, radio) if m.n_points)
    xy, floor = wknn_scans(Fingerprints(maps, wknn.missing_dbm), located, replace(wknn, k=k))
    right = floor == located.scan_floor
    # e = |x̂ - x| on the right floor, the wrong-floor figure otherwise
    actual = np.where(right, np.hypot(*(xy - located.scan_xy).T), params.wrong_floor_m)
    expected, on_grid = expected_at(grids, located.scan_floor, located.scan_xy)
    walkable = sum(int(g.walkable.sum()) for g in grids.values())
    rows = []
    for lo, hi in zip(BINS_M[:-1], BINS_M[1:], strict=True):
        cells = sum(
            int((g.walkable & (g.error_m >= lo) & (g.error_m < hi)).sum()) for g in grids.values()
        )
        pick = on_grid & (expected >= lo) & (expected < hi)
        label = f"≥ {lo:g} m" if np.isinf(hi) else f"{lo:g}–{hi:g} m"
        rows.append(_row(label, cells / walkable, expected[pick], actual[pick], ~right[pick]))
    unsurveyed = sum(int(g.unsurveyed.sum()) for g in grids.values())
    pick = on_grid & np.isnan(expected)
    rows.append(
        _row("unsurveyed", unsurveyed / walkable, expected[pick], actual[pick], ~right[pick])
    )
    pick = ~on_grid
    rows.append(_row("off the walkable cells", 0.0, expected[pick], actual[pick], ~right[pick]))
    scored = on_grid & np.isfinite(expected)
    rho = spearmanr(expected[scored], actual[scored]).statistic if scored.sum() > 2 else np.nan
    print(
        f"{len(floors)} floors, {len(surveyed)} surveyed walks ({survey.n_scans} scans, k = {k}), "
        f"{len(held)} held-out walks ({located.n_scans} scans); cell {params.cell_m:g} m, "
        f"bandwidth {params.bandwidth_m:g} m, reach {params.reach_m:g} m"
    )
    if args.markdown:
        print(markdown_table(COLUMNS, rows))
    else:
        width = [max(len(str(r[i])) for r in [list(COLUMNS), *rows]) for i in range(len(COLUMNS))]
        for r in [list(COLUMNS), *rows]:
            print("  ".join(str(c).rjust(w) for c, w in zip(r, width, strict=True)))
    print(f"Spearman rank correlation of expected and actual error, surveyed cells: {rho:.3f}")
    reach = other_fold_distance(survey, cv.by_k[k]) <= params.reach_m
    errors = scan_errors(cv.by_k[k], params.wrong_floor_m)
    print(
        f"the build's held-out scans with another fold's scan within {params.reach_m:g} m: "
        f"{100 * np.mean(reach):.1f}%, mean error {np.mean(errors[reach]):.2f} m; "
        f"the others {np.mean(errors[~reach]):.2f} m"
    )


if __name__ == "__main__":
    main()
