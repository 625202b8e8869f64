"""The smoother: positions weighed against the steps that join them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from app.engine.samples import Estimate
from app.engine.smoothing import (
    FixedLagSmoother,
    SmootherParams,
    fixed_lag,
    smooth_positions,
    smooth_track,
)
from app.workers.snapshots import decode, encode

PARAMS = SmootherParams()


def _walk(n: int = 120, seed: int = 5, noise_m: float = 3.0) -> tuple[list[Estimate], np.ndarray]:
    """A walk along an L at 1.2 m/s, a fix every 0.5 s with noise, odometry with a 10% scale
    error; returns the estimates and the true positions."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 500
    s = 1.2 * t / 1000.0
    truth = np.where(s[:, None] < 30.0, np.stack([s, 0 * s], 1), np.stack([30 + 0 * s, s - 30], 1))
    odometry = 1.1 * truth + np.array([7.0, -3.0])
    fixes = truth + rng.normal(0.0, noise_m, truth.shape)
    estimates = [
        Estimate(
            t=int(t[i]),
            x=float(fixes[i, 0]),
            y=float(fixes[i, 1]),
            z=0.0,
            floor=0,
            heading=float("nan"),
            accuracy=noise_m * 1.515,
            speed=1.2,
            method="hmm",
            odometry=(float(odometry[i, 0]), float(odometry[i, 1])),
        )
        for i in range(n)
    ]
    return estimates, truth


def _error(estimates: list[Estimate], truth: np.ndarray) -> float:
    xy = np.array([[e.x, e.y] for e in estimates])
    return float(np.mean(np.hypot(*(xy - truth).T)))


def test_smoothing_a_noisy_track_with_its_steps_brings_it_closer_to_the_truth() -> None:
    estimates, truth = _walk()
    raw = _error(estimates, truth)
    lagged = _error(fixed_lag(estimates, PARAMS), truth)
    full = _error(smooth_track(estimates, PARAMS), truth)
    # steps tie neighbouring fixes together: the noise averages out
    assert full < 0.5 * raw
    assert lagged < 0.6 * raw
    # the full pass knows at least as much as the lagged one
    assert full <= lagged + 0.1


def test_without_steps_the_smoother_only_bounds_speed() -> None:
    estimates, truth = _walk(noise_m=2.0)
    blind = [
        Estimate(**{**vars(e), "odometry": None})  # type: ignore[arg-type]
        for e in estimates
    ]
    # still better than the raw fixes (walking speed is bounded), but less than with steps
    assert _error(smooth_track(blind, PARAMS), truth) < _error(estimates, truth)
    assert _error(smooth_track(estimates, PARAMS), truth) < _error(
        smooth_track(blind, PARAMS), truth
    )


def test_exact_fixes_are_kept_and_a_lone_fix_is_unchanged() -> None:
    t = np.array([0, 1000, 2000])
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    odo = xy.copy()
    out = smooth_positions(t, xy, np.full(3, 0.5), odo, PARAMS)
    assert np.allclose(out, xy)
    one = smooth_positions(t[:1], xy[:1], np.ones(1), odo[:1], PARAMS)
    assert np.array_equal(one, xy[:1])


def test_floor_changes_split_the_track() -> None:
    estimates, _ = _walk(n=20)
    moved = [
        Estimate(**{**vars(e), "floor": 0 if i < 10 else 1})  # type: ignore[arg-type]
        for i, e in enumerate(estimates)
    ]
    alone = smooth_track(moved[10:], PARAMS)
    together = smooth_track(moved, PARAMS)[10:]
    assert [(e.x, e.y) for e in alone] == [(e.x, e.y) for e in together]


def test_the_live_smoother_re_emits_each_position_as_the_fixed_lag_pass_refines_it() -> None:
    estimates, _ = _walk(n=80)
    expected = fixed_lag(estimates, PARAMS)
    smoother = FixedLagSmoother(PARAMS)
    got: list[Estimate] = []
    for lo in range(0, len(estimates), 3):
        got += smoother.push(estimates[lo : lo + 3])
        # a restart in between resumes from the snapshot
        smoother = FixedLagSmoother(PARAMS, snapshot_roundtrip(smoother.snapshot()))
    got += smoother.flush()
    assert all(e.smoothed for e in got)
    assert [e.t for e in got] == [e.t for e in estimates]
    # the same solves as the whole-track fixed-lag pass, up to the window's edge
    xy = np.array([[e.x, e.y] for e in got])
    ref = np.array([[e.x, e.y] for e in expected])
    assert np.allclose(xy, ref, atol=1e-9)
    # nothing is emitted twice
    assert smoother.flush() == [] and smoother.push([]) == []


def snapshot_roundtrip(state: dict) -> dict:
    """The smoother's state as a device snapshot stores and reads it."""
    return decode(encode(state))


def test_filter_positions_whose_errors_persist_count_less_under_a_larger_fix_scale() -> None:
    """A filter's position carries the scans before it, so its error lasts from one
    position to the next; weighed as independent fixes the track follows that error,
    while a larger σ lets the steps average it over a longer stretch."""
    estimates, truth = _walk(n=240, seed=11, noise_m=0.0)
    rng = np.random.default_rng(3)
    drift = np.zeros((len(estimates), 2))
    for i in range(1, len(estimates)):
        # an AR(1) error of about 3 m that decorrelates over ~20 positions
        drift[i] = 0.95 * drift[i - 1] + rng.normal(0.0, 3.0 * np.sqrt(1 - 0.95**2), 2)
    odometry = truth + np.array([7.0, -3.0])
    persistent = [
        replace(e, x=float(p[0]), y=float(p[1]), accuracy=4.5, odometry=(float(o[0]), float(o[1])))
        for e, p, o in zip(estimates, truth + drift, odometry, strict=True)
    ]
    errors = {
        scale: _error(smooth_track(persistent, SmootherParams(fix_scale=scale)), truth)
        for scale in (1.0, 4.0)
    }
    assert errors[4.0] < 0.8 * errors[1.0]
    assert errors[1.0] < _error(persistent, truth)


def test_the_compiled_solve_is_the_least_squares_track() -> None:
    """The elimination returns what a dense solve of the same normal equations returns,
    with a stretch without odometry (speed-bounded) and an unbounded fix among them."""
    estimates, _ = _walk(n=30, seed=8)
    t = np.array([e.t for e in estimates])
    xy = np.array([[e.x, e.y] for e in estimates])
    sigma = np.linspace(0.5, 6.0, t.size)
    sigma[7] = np.inf
    odo = np.array([e.odometry for e in estimates], dtype=float)
    odo[12:15] = np.nan
    p = SmootherParams(fix_scale=2.0)
    step = np.diff(odo, axis=0)
    known = np.all(np.isfinite(step), axis=1)
    dt = np.diff(t) / 1000.0
    m = np.where(known, p.motion_std_m + p.motion_std_per_s * dt, p.motion_std_m + 1.5 * dt)
    step = np.where(known[:, None], step, 0.0)
    difference = np.diff(np.eye(t.size), axis=0)
    w_fix = np.diag(1.0 / np.maximum(p.fix_scale * sigma, p.fix_floor_m) ** 2)
    w_mot = np.diag(1.0 / m**2)
    lhs = w_fix + difference.T @ w_mot @ difference
    rhs = w_fix @ xy + difference.T @ w_mot @ step
    assert np.allclose(smooth_positions(t, xy, sigma, odo, p), np.linalg.solve(lhs, rhs))


def test_positions_sharing_a_time_are_refined_once_as_the_first_was_reported() -> None:
    """A step and a scan can fall on the same millisecond: the stream emits the first, and
    the refined stream refines that one, once."""
    estimates, _ = _walk(n=30)
    twin = replace(estimates[10], x=estimates[10].x + 50.0)
    smoother = FixedLagSmoother(PARAMS)
    got = smoother.push([*estimates[:11], twin, *estimates[11:]]) + smoother.flush()
    assert [e.t for e in got] == [e.t for e in estimates]
    assert np.allclose(
        [[e.x, e.y] for e in got], [[e.x, e.y] for e in fixed_lag(estimates, PARAMS)]
    )
