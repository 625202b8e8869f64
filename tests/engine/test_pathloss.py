"""Path loss: model, inverse, quality filter at S_q, fit, likelihood, expected-RSSI raster."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.pathloss import (
    PathLossParams,
    build_rssi_grid,
    expected_rssi,
    fit_pathloss,
    grid_log_likelihood,
    log_likelihood,
    range_from_rssi,
    ranges_3d,
    reliable,
)


def test_model_and_inverse_match_hand_values_and_round_trip() -> None:
    # rssi(e²) = A - 2B; r(A - B) = e
    assert expected_rssi(np.e**2, -40.0, 20.0) == pytest.approx(-80.0)
    assert range_from_rssi(-60.0, -40.0, 20.0) == pytest.approx(np.e)
    r = np.array([0.5, 1.0, 3.7, 42.0])
    assert range_from_rssi(expected_rssi(r, -47.0, 13.0), -47.0, 13.0) == pytest.approx(r)


def test_quality_filter_keeps_ratio_at_threshold_and_drops_above() -> None:
    sigma = np.array([15.0, 15.0 + 1e-9, 3.0, 3.0, np.nan])
    b = np.array([10.0, 10.0, 0.0, np.nan, 10.0])
    # σ / B = 1.5 exactly passes ("exceeds" drops), a hair above is dropped, no model fails
    assert reliable(sigma, b, 1.5).tolist() == [True, False, False, False, False]


def test_fit_recovers_parameters_of_synthetic_readings() -> None:
    rng = np.random.default_rng(3)
    r = rng.uniform(1.0, 30.0, 20_000)
    rssi = expected_rssi(r, -43.0, 17.0) + rng.normal(0.0, 4.0, r.size)
    a, b, sigma = fit_pathloss(r, rssi, 0.5)
    # standard errors at n = 20,000 are below 0.1 dB for A and B
    assert a == pytest.approx(-43.0, abs=0.3)
    assert b == pytest.approx(17.0, abs=0.3)
    assert sigma == pytest.approx(4.0, abs=0.1)


def test_fit_without_noise_is_exact_and_clamps_short_ranges() -> None:
    r = np.array([0.1, 2.0, 5.0, 9.0])
    rssi = expected_rssi(np.maximum(r, 0.5), -50.0, 10.0)
    a, b, sigma = fit_pathloss(r, rssi, 0.5)
    assert (a, b, sigma) == pytest.approx((-50.0, 10.0, 0.0), abs=1e-9)


def test_log_likelihood_equals_sum_of_gaussian_log_densities() -> None:
    s = np.array([-60.0, -72.5, -81.0])
    mu = np.array([-58.0, -75.0, -90.0])
    sd = np.array([4.0, 6.0, 5.0])
    ref = sum(
        np.log(np.exp(-((si - mi) ** 2) / (2 * di * di)) / (di * np.sqrt(2 * np.pi)))
        for si, mi, di in zip(s, mu, sd, strict=True)
    )
    assert log_likelihood(s, mu, sd) == pytest.approx(ref, rel=1e-12)


def test_ranges_are_3d_with_receiver_height_and_clamped() -> None:
    tx = np.array([[3.0, 4.0, 2.2], [0.0, 0.0, 1.2]])
    r = ranges_3d(np.array([[0.0, 0.0]]), tx, 1.2, 0.5)
    assert r[0].tolist() == pytest.approx([np.sqrt(25.0 + 1.0), 0.5])


def _grid_case() -> tuple:
    rng = np.random.default_rng(5)
    tx_xyz = np.column_stack([rng.uniform(0, 20, 7), rng.uniform(0, 10, 7), np.full(7, 2.5)])
    a = rng.uniform(-50, -40, 7)
    b = rng.uniform(12, 22, 7)
    params = PathLossParams(grid_cell_m=0.5)
    grid = build_rssi_grid((0.0, 0.0, 20.0, 10.0), tx_xyz, a, b, params)
    return rng, tx_xyz, a, b, params, grid


def test_grid_holds_model_rssi_at_cell_centres_within_half_a_code() -> None:
    _, tx_xyz, a, b, params, grid = _grid_case()
    ny, nx = grid.shape
    assert (ny, nx) == (20, 40)
    centres = np.stack(
        np.meshgrid((np.arange(nx) + 0.5) * 0.5, (np.arange(ny) + 0.5) * 0.5), axis=-1
    ).reshape(-1, 2)
    exact = expected_rssi(ranges_3d(centres, tx_xyz, 1.2, 0.5), a, b)
    assert np.abs(grid.decode(grid.codes) - exact).max() <= params.code_step_db / 2 + 1e-9
    assert grid.cell_index(
        np.array([0.26, 19.99, -3.0]), np.array([0.01, 9.99, 50.0])
    ).tolist() == [
        0,
        ny * nx - 1,
        (ny - 1) * nx,
    ]


def test_grid_likelihood_matches_direct_gaussian_sum_over_decoded_values() -> None:
    rng, _, _, _, _, grid = _grid_case()
    d, n, m = 5, 300, 4
    x = rng.uniform(0, 20, (d, n))
    y = rng.uniform(0, 10, (d, n))
    cells = grid.cell_index(x, y)
    tx = np.stack([rng.choice(7, m, replace=False) for _ in range(d)])
    rssi = rng.uniform(-90, -50, (d, m))
    count = rng.integers(1, 4, (d, m)).astype(float)
    sigma = rng.uniform(3, 8, (d, m))
    weight = count / (2 * sigma**2)
    weight[0, -1] = 0.0  # padding contributes nothing
    ll = grid_log_likelihood(grid, cells, tx, rssi, weight)
    mu = grid.decode(grid.codes[cells[:, None, :], tx[:, :, None]])
    ref = -np.sum(weight[:, :, None] * (rssi[:, :, None] - mu) ** 2, axis=1)
    np.testing.assert_allclose(ll, ref, rtol=2e-5, atol=1e-3)


def test_grid_likelihood_of_a_row_does_not_depend_on_the_padding_of_others() -> None:
    # A float32 dot product padded with zeros rounds differently in BLAS (here a
    # row hearing 4 of a 5-wide table did); each row must give the same bits
    # alone as beside rows hearing more, or resampling turns the last bit into
    # a different track depending on the device's batch mates.
    rng = np.random.default_rng(5)
    t = 40
    tx_xyz = np.column_stack([rng.uniform(0, 60, t), rng.uniform(0, 30, t), np.full(t, 2.5)])
    a, b = rng.uniform(-50, -40, t), rng.uniform(12, 22, t)
    grid = build_rssi_grid((0.0, 0.0, 60.0, 30.0), tx_xyz, a, b, PathLossParams(grid_cell_m=0.5))
    d, n, m = 10, 1000, 5
    cells = grid.cell_index(rng.uniform(0, 60, (d, n)), rng.uniform(0, 30, (d, n)))
    tx = np.stack([rng.choice(t, m, replace=False) for _ in range(d)])
    rssi = rng.uniform(-90, -50, (d, m))
    weight = rng.uniform(0.01, 0.05, (d, m))
    heard = np.arange(d) % m + 1
    weight[np.arange(m)[None, :] >= heard[:, None]] = 0.0
    together = grid_log_likelihood(grid, cells, tx, rssi, weight)
    for r, k in enumerate(heard.tolist()):
        alone = grid_log_likelihood(
            grid, cells[r : r + 1], tx[r : r + 1, :k], rssi[r : r + 1, :k], weight[r : r + 1, :k]
        )
        np.testing.assert_array_equal(alone[0], together[r], err_msg=f"row {r} hearing {k}")
