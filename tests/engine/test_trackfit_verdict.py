"""Fitted or not: an open hall leaves the rotation open, a corridor's turn pins it; a compass
with a constant bias is followed and its bias estimated."""

from __future__ import annotations

import numpy as np

from app.engine.plan import FloorPlan
from app.engine.trackfit.search import search_track
from app.engine.trackfit.verdict import VerdictParams, judge
from tests.engine.test_trackfit_search import PLAN, ROUTE, resample


def _raster(free: np.ndarray, cell: float = 0.25) -> FloorPlan:
    return FloorPlan.from_raster(origin=np.zeros(2), cell=cell, free=free)


def test_a_track_in_an_open_hall_comes_back_unfitted_with_its_reason() -> None:
    free = np.ones((160, 160), dtype=bool)
    free[[0, -1], :] = free[:, [0, -1]] = False
    found = search_track(_raster(free), np.array([20.0, 20.0]), np.full(10, 1.0), np.zeros(10))
    verdict = judge(found, np.full(10, 1.0), oriented=False, params=VerdictParams())
    assert not verdict.fitted
    assert verdict.reason is not None and "rotation" in verdict.reason
    # the radius grows with the distance walked
    assert np.all(np.diff(verdict.radius) > 0)


def test_a_track_down_a_corridor_with_one_turn_comes_back_fitted() -> None:
    # an L of 2 m corridors: 30 m east along y = 1 … 3, then 20 m north along x = 28 … 30
    free = np.zeros((140, 140), dtype=bool)
    free[4:12, 4:120] = True
    free[4:100, 112:120] = True
    plan = _raster(free)
    truth = resample(np.array([[2.0, 2.0], [29.0, 2.0], [29.0, 22.0]]), 47)
    d = np.diff(truth, axis=0)
    lengths = np.hypot(*d.T) * 1.05
    direction = np.arctan2(d[:, 1], d[:, 0])
    turns = np.r_[0.0, np.diff(direction)]
    found = search_track(plan, truth[0], lengths, turns)
    verdict = judge(found, lengths, oriented=False, params=VerdictParams())
    assert verdict.fitted, verdict.reason
    error = np.hypot(*(found.best.fit.points - truth).T)
    assert error.mean() < 1.0, error.mean()


def test_a_per_link_compass_with_a_20_degree_bias_is_followed_and_its_bias_estimated() -> None:
    rng = np.random.default_rng(20)
    truth = resample(ROUTE, 171)
    d = np.diff(truth, axis=0)
    true_dir = np.arctan2(d[:, 1], d[:, 0])
    n = true_dir.size
    # the gyro's heading wanders 2° a link; the compass reads the truth + 20° ± 5°
    dr_dir = true_dir + np.cumsum(rng.normal(0.0, np.radians(2.0), n))
    turns = np.r_[0.0, np.diff(dr_dir)]
    lengths = np.hypot(*d.T) * (1.0 + rng.normal(0.0, 0.03, n))
    compass = true_dir + np.radians(20.0) + rng.normal(0.0, np.radians(5.0), n)
    times = 0.6 * np.arange(n + 1)
    found = search_track(
        PLAN, truth[0], lengths, turns, times=times, compass=compass, compass_sigma=np.radians(5)
    )
    assert found.bias is not None
    assert abs(np.degrees(found.bias) - 20.0) <= 5.0, np.degrees(found.bias)
    error = np.hypot(*(found.best.fit.points - truth).T)
    assert error.mean() < 1.0, error.mean()
    verdict = judge(found, lengths, oriented=True, params=VerdictParams())
    assert verdict.fitted, verdict.reason
