"""Survey guidance: held-out errors smoothed over a floor, against a dense second computation
and a corridor surveyed well at one end, on a wrong floor in the middle, not at all beyond."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.crossval import HeldOut
from app.engine.plan import FloorPlan
from app.engine.radiomap import Survey
from app.engine.survey_guidance import (
    KERNEL_CUTOFF_SIGMAS,
    GuidanceParams,
    floor_guidance,
    scan_errors,
    site_guidance,
    smoothed_errors,
)

PARAMS = GuidanceParams()


def corridor() -> FloorPlan:
    """A 40 × 10 m floor at 0.5 m cells whose top 2 m are blocked (a wall zone)."""
    free = np.ones((20, 80), dtype=bool)
    free[16:, :] = False
    return FloorPlan.from_raster(origin=np.zeros(2), cell=0.5, free=free)


def walked(x0: float, x1: float, step: float = 1.0) -> np.ndarray:
    """Return scan positions every ``step`` m along y = 4 from x0 to x1."""
    x = np.arange(x0, x1 + 1e-9, step)
    return np.column_stack([x, np.full(x.size, 4.0)])


def survey_of(xy: np.ndarray, floor: np.ndarray) -> Survey:
    """Return a survey of located scans with no readings (the guidance reads none)."""
    n = xy.shape[0]
    none = np.zeros(0, dtype=np.int32)
    return Survey(
        scan_t=np.arange(n, dtype=np.int64) * 2000,
        scan_xy=xy,
        scan_floor=floor.astype(np.int32),
        scan_walk=np.zeros(n, dtype=np.int32),
        reading_scan=none,
        reading_tx=none,
        reading_rssi=np.zeros(0),
    )


def dense_reference(points: np.ndarray, xy: np.ndarray, e: np.ndarray, params: GuidanceParams):
    """The same estimate from the full (points × scans) distance matrix."""
    d = np.linalg.norm(points[:, None, :] - xy[None, :, :], axis=-1)
    w = np.where(
        d <= KERNEL_CUTOFF_SIGMAS * params.bandwidth_m,
        np.exp(-0.5 * (d / params.bandwidth_m) ** 2),
        0.0,
    )
    nearest = d.min(axis=1)
    with np.errstate(invalid="ignore"):
        value = (w * e).sum(axis=1) / w.sum(axis=1)
    return np.where(nearest <= params.reach_m, value, np.nan), nearest


def test_smoothed_errors_match_a_dense_computation() -> None:
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 30, size=(200, 2))
    e = rng.gamma(2.0, 2.0, size=200)
    points = rng.uniform(-10, 40, size=(500, 2))
    error, distance = smoothed_errors(points, xy, e, PARAMS.bandwidth_m, PARAMS.reach_m)
    want_error, want_distance = dense_reference(points, xy, e, PARAMS)
    np.testing.assert_allclose(distance, want_distance, rtol=1e-12)
    assert np.array_equal(np.isnan(error), np.isnan(want_error))
    assert np.isnan(error).any() and np.isfinite(error).any()
    np.testing.assert_allclose(error, want_error, rtol=1e-12, equal_nan=True)


def test_a_wrong_floor_counts_as_the_wrong_floor_error() -> None:
    held = HeldOut(
        error_m=np.array([1.5, 3.0, 0.2]),
        floor_ok=np.array([True, False, True]),
        scan=np.arange(3),
        folds=2,
    )
    assert scan_errors(held, 20.0).tolist() == [1.5, 20.0, 0.2]


def test_a_well_surveyed_end_is_low_a_wrong_floor_middle_high_and_the_far_end_unsurveyed() -> None:
    plan = corridor()
    good, wrong = walked(1.0, 15.0), walked(17.0, 23.0)
    xy = np.vstack([good, wrong])
    held = HeldOut(
        error_m=np.r_[np.full(len(good), 2.0), np.full(len(wrong), 3.0)],
        floor_ok=np.r_[np.ones(len(good), bool), np.zeros(len(wrong), bool)],
        scan=np.arange(len(xy)),
        folds=5,
    )
    grids = site_guidance(survey_of(xy, np.zeros(len(xy))), held, {0: plan, 1: plan})
    grid = grids[0]
    assert grid.shape == (5, 20) and grid.cell == PARAMS.cell_m and grid.scans == len(xy)
    # the blocked top 2 m (row 4) is not walkable: null in both grids
    assert not grid.walkable[4].any() and grid.walkable[:4].all()
    assert np.isnan(grid.error_m[4]).all() and np.isnan(grid.distance_m[4]).all()
    x = grid.origin[0] + (np.arange(20) + 0.5) * grid.cell
    row = grid.error_m[2]  # y 4–6 m, along the walked line
    # among scans that all erred 2 m, 2 m is expected
    np.testing.assert_allclose(row[x < 8], 2.0, rtol=1e-12)
    # scans placed on a wrong floor make their stretch as bad as a wrong floor
    assert np.all(row[(x > 19) & (x < 22)] > 15.0)
    assert np.all(row[(x > 19) & (x < 22)] > PARAMS.high_error_m)
    # beyond reach of every scan: unsurveyed, with its distance from the survey
    far = x > 23.0 + PARAMS.reach_m
    assert far.any() and np.isnan(grid.error_m[:4, far]).all()
    assert grid.unsurveyed[:4, far].all() and not grid.unsurveyed[:4, x < 20].any()
    np.testing.assert_allclose(grid.distance_m[2, far], np.hypot(x[far] - 23.0, 5.0 - 4.0))
    assert grid.high[:4].sum() > 0 and not grid.high[:4, x < 12].any()
    # a floor with no held-out scan is unsurveyed everywhere it is walkable
    other = grids[1]
    assert other.scans == 0 and other.unsurveyed.sum() == other.walkable.sum() > 0
    assert np.isinf(other.distance_m[other.walkable]).all()


@pytest.mark.parametrize("cell", [1.0, 2.5])
def test_the_grid_follows_the_cell_size(cell: float) -> None:
    plan = corridor()
    xy = walked(1.0, 39.0)
    grid = floor_guidance(plan, xy, np.full(len(xy), 4.0), GuidanceParams(cell_m=cell))
    ny, nx = grid.shape
    assert (ny, nx) == (int(np.ceil(10 / cell)), int(np.ceil(40 / cell)))
    assert np.allclose(grid.error_m[grid.walkable & (grid.distance_m <= 3.0)], 4.0)
