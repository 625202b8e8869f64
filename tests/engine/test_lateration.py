"""Lateration: exact fixes, closed-form covariances, robustness, and every degenerate input."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.lateration.accuracy import (
    covariance_checks,
    critical_condition,
    path_loss_B,
    predict,
    whitened_jacobian,
)
from app.engine.lateration.solver import (
    LaterationParams,
    Status,
    laterate_ranges,
    laterate_rssi,
    solve,
)

ROOM = np.array(
    [
        [0.0, 0.0, 2.5],
        [10.0, 0.0, 2.6],
        [10.0, 8.0, 2.4],
        [0.0, 8.0, 2.7],
        [5.0, -1.0, 0.5],
        [5.0, 9.0, 0.3],
    ]
)


def _ranges(anchors: np.ndarray, p: np.ndarray) -> np.ndarray:
    return np.linalg.norm(anchors - p, axis=1)


def test_noiseless_ranges_give_the_point_in_2d_and_3d() -> None:
    p = np.array([3.0, 4.0, 1.2])
    flat = laterate_ranges(ROOM, _ranges(ROOM, p), 0.05, height=1.2, dims=2)
    full = laterate_ranges(ROOM, _ranges(ROOM, p), 0.05, height=1.0, dims=3)
    assert flat.ok and full.ok
    assert flat.dims == 2 and full.dims == 3
    np.testing.assert_allclose(flat.position, p, atol=1e-6)
    np.testing.assert_allclose(full.position, p, atol=1e-6)
    assert flat.converged and flat.iterations <= 10
    np.testing.assert_allclose(flat.residuals, 0.0, atol=1e-6)


def test_range_covariance_matches_the_hand_worked_cross() -> None:
    # anchors at ±d along x and y in the object's plane: HᵀH = 2 I / σ², so σx = σy = σ/√2
    p = np.array([2.0, 3.0, 1.0])
    anchors = p + np.array([[4.0, 0, 0], [-4.0, 0, 0], [0, 4.0, 0], [0, -4.0, 0]])
    fix = laterate_ranges(anchors, _ranges(anchors, p), 0.1, height=1.0, dims=2)
    np.testing.assert_allclose(fix.covariance[:2, :2], np.eye(2) * 0.1**2 / 2, rtol=1e-9)
    assert fix.covariance[2, 2] == 0.0
    assert fix.cond == pytest.approx(1.0)


def test_rssi_fix_and_covariance_match_the_closed_form() -> None:
    # rssi = A − B ln d; H rows −B (p − e)/d²: for the same cross, σx = σ d / (B √2) per reading,
    # and M readings divide the variance by M (Grinyak 2020)
    p = np.array([5.0, 5.0, 1.5])
    d = 3.0
    tx = p + np.array([[d, 0, 0], [-d, 0, 0], [0, d, 0], [0, -d, 0]])
    A = np.full(4, -59.0)
    B = np.full(4, path_loss_B(2.0))
    rssi = A - B * np.log(_ranges(tx, p))
    fix = laterate_rssi(tx, rssi, A, B, np.full(4, 5.0), count=50, height=1.5, dims=2)
    assert fix.ok
    np.testing.assert_allclose(fix.position, p, atol=1e-6)
    sigma = 5.0 / np.sqrt(50) * d / (B[0] * np.sqrt(2))
    np.testing.assert_allclose(fix.sigma[:2], [sigma, sigma], rtol=1e-9)


def test_path_loss_slope_of_the_paper_exponent() -> None:
    # u = u* − 10 n log10 d = u* − (10 n / ln 10) ln d
    assert path_loss_B(2.0) == pytest.approx(20.0 / np.log(10.0))
    d = np.array([1.0, 2.0, 7.5])
    np.testing.assert_allclose(
        -60 - path_loss_B(2.7) * np.log(d), -60 - 10 * 2.7 * np.log10(d), atol=1e-12
    )


def test_jacobian_agrees_with_finite_differences() -> None:
    rng = np.random.default_rng(3)
    points = rng.uniform(0, 8, (5, 3))
    A = rng.uniform(-65, -55, ROOM.shape[0])
    B = rng.uniform(6, 12, ROOM.shape[0])
    for model in ("range", "rssi"):
        _, J = predict(model, points, ROOM, A, B)
        h = 1e-6
        for k in range(3):
            step = np.zeros(3)
            step[k] = h
            up, _ = predict(model, points + step, ROOM, A, B)
            down, _ = predict(model, points - step, ROOM, A, B)
            np.testing.assert_allclose(J[..., k], (up - down) / (2 * h), atol=1e-6)


def test_huber_bounds_and_cauchy_removes_an_nlos_range() -> None:
    rng = np.random.default_rng(7)
    p = np.array([6.0, 3.0, 1.0])
    r = _ranges(ROOM, p) + rng.normal(0.0, 0.03, ROOM.shape[0])
    r[0] += 2.0  # a range through a wall
    errors = {}
    for loss in ("linear", "huber", "cauchy"):
        fix = laterate_ranges(ROOM, r, 0.05, height=1.0, dims=2, params=LaterationParams(loss=loss))
        errors[loss] = np.hypot(*(fix.position[:2] - p[:2]))
        if loss != "linear":
            assert fix.weights[0] < 0.1 * fix.weights[1:].min()
    clean = r.copy()
    clean[0] = np.nan
    oracle = laterate_ranges(ROOM, clean, 0.05, height=1.0, dims=2)
    oracle_error = np.hypot(*(oracle.position[:2] - p[:2]))
    assert errors["linear"] > 0.5
    # Huber's influence is bounded (k σ), not zero; Cauchy's redescends
    assert errors["huber"] < errors["linear"] / 5
    assert abs(errors["cauchy"] - oracle_error) < 0.01


def test_fewer_anchors_than_needed_give_no_fix() -> None:
    p = np.array([3.0, 4.0, 1.0])
    two = laterate_ranges(ROOM[:2], _ranges(ROOM[:2], p), 0.05, height=1.0, dims=2)
    assert two.status == Status.TOO_FEW and not two.ok
    assert np.isnan(two.position).all() and np.isnan(two.covariance).all()
    three = laterate_ranges(ROOM[:3], _ranges(ROOM[:3], p), 0.05, dims=3)
    assert three.status == Status.TOO_FEW  # 3-D needs 4


def test_nan_ranges_and_stds_are_ignored() -> None:
    p = np.array([3.0, 4.0, 1.0])
    r = _ranges(ROOM, p)
    r[[1, 4]] = np.nan
    std = np.full(ROOM.shape[0], 0.05)
    std[2] = np.nan
    fix = laterate_ranges(ROOM, r, std, height=1.0, dims=2)
    assert fix.ok
    np.testing.assert_allclose(fix.position, p, atol=1e-6)
    assert np.isnan(fix.residuals[[1, 2, 4]]).all() and (fix.weights[[1, 2, 4]] == 0).all()
    r[[0, 3, 5]] = np.nan
    assert laterate_ranges(ROOM, r, std, height=1.0, dims=2).status == Status.TOO_FEW


def test_collinear_anchors_are_flagged() -> None:
    line = np.array([[0.0, 0.0, 1.0], [4.0, 0.0, 1.0], [9.0, 0.0, 1.0]])
    p = np.array([3.0, 2.0, 1.0])
    fix = laterate_ranges(line, _ranges(line, p), 0.05, height=1.0, dims=2)
    assert fix.status == Status.DEGENERATE and not fix.ok


def test_object_in_the_anchors_plane_falls_back_to_the_known_height() -> None:
    plane = np.array([[0.0, 0, 1.0], [10, 0, 1.0], [10, 8, 1.0], [0, 8, 1.0], [5, -2, 1.0]])
    p = np.array([3.0, 4.0, 1.0])
    fix = laterate_ranges(plane, _ranges(plane, p), 0.05, height=1.0, dims=3)
    assert fix.ok and fix.dims == 2
    np.testing.assert_allclose(fix.position, p, atol=1e-6)
    blind = laterate_ranges(plane, _ranges(plane, p), 0.05, dims=3)
    assert blind.status == Status.UNOBSERVABLE and blind.dims == 3


def test_rank_and_condition_checks() -> None:
    Hw = np.array([[[1.0, 0.0], [0.0, 2.0], [0.0, 0.0]], [[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]])
    cov, cond, rank = covariance_checks(Hw)
    np.testing.assert_allclose(cov[0], np.diag([1.0, 0.25]))
    assert cond[0] == pytest.approx(2.0)
    assert rank.tolist() == [2, 1]
    assert np.isinf(cond[1]) and np.isnan(cov[1]).all()
    # μ* of Grinyak 2020: about 10¹³ for u = 6 in double precision
    assert 1e12 < critical_condition(6) < 1e14
    u = 3
    assert critical_condition(u, 1e-16) == pytest.approx(
        1 / ((np.sqrt(u) * (2 * u - 3) * (4 * u + 27) + 11) * 1e-16)
    )


def test_whitened_jacobian_of_unheard_emitters_is_zero() -> None:
    points = np.array([[1.0, 1.0, 1.0]])
    Hw = whitened_jacobian("range", points, ROOM, np.array([0.1, np.nan, np.inf, 0.1, 0, 0.2]))
    assert (Hw[0, [1, 2, 4]] == 0).all() and (Hw[0, [0, 3, 5]] != 0).any()


def test_batch_equals_one_problem_at_a_time() -> None:
    rng = np.random.default_rng(11)
    truth = np.column_stack([rng.uniform(1, 9, 40), rng.uniform(1, 7, 40), np.full(40, 1.1)])
    obs = np.linalg.norm(truth[:, None] - ROOM[None], axis=-1) + rng.normal(0, 0.1, (40, 6))
    obs[rng.random(obs.shape) < 0.15] = np.nan
    batch = solve("range", ROOM, obs, np.full(6, 0.1), height=1.1, dims=2)
    for i in range(40):
        one = laterate_ranges(ROOM, obs[i], 0.1, height=1.1, dims=2)
        assert one.status == batch.status[i]
        np.testing.assert_allclose(one.position, batch.position[i], atol=1e-9, equal_nan=True)
        np.testing.assert_allclose(one.covariance, batch.covariance[i], atol=1e-12, equal_nan=True)


def test_hopeless_rssi_never_raises() -> None:
    # readings far weaker than any position inside could produce: the cost is flat outwards
    tx = np.array([[0.0, 0, 2], [10, 0, 2], [10, 10, 2], [0, 10, 2]])
    A = np.full(4, -40.0)
    B = np.full(4, 8.0)
    rssi = np.array([-140.0, -139.0, -141.0, -140.5])
    fix = laterate_rssi(tx, rssi, A, B, np.full(4, 5.0), height=1.0, dims=2)
    assert np.isfinite(fix.position).all() or fix.status != Status.OK
    # NaN path-loss parameters take the emitter out instead of poisoning the fix
    A[0] = np.nan
    p = np.array([4.0, 6.0, 1.0])
    clean = -40.0 - 8.0 * np.log(_ranges(tx, p))
    fix = laterate_rssi(tx, clean, A, B, np.full(4, 5.0), height=1.0, dims=2)
    assert fix.ok and np.isnan(fix.residuals[0])
    np.testing.assert_allclose(fix.position, p, atol=1e-6)
