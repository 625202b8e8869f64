"""Transmitter calibration on synthetic walks with known truth: position, A, B and sigma are
recovered from noisy readings censored below -95 dBm; a known position is kept; the floor
is the one with the strongest readings."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize._numdiff import approx_derivative

from app.engine.calibration import (
    CalibrationParams,
    _jacobian,
    _residuals,
    calibrate,
    distances,
    fit_path_loss,
    transmitter_floor,
)
from app.engine.pathloss import expected_rssi
from app.engine.radiomap import Survey

PARAMS = CalibrationParams()
DZ = PARAMS.tx_height_m - PARAMS.rx_height_m
SENSITIVITY = -95.0


def _walk_grid(step: float = 1.0) -> np.ndarray:
    """Scan positions of a lawnmower survey over a 40 × 24 m hall, one every ``step`` m."""
    xs = np.arange(0.5, 40.0, step)
    ys = np.arange(0.5, 24.0, 2.0)
    return np.array([(x, y) for y in ys for x in xs], dtype=float)


def _survey(
    scan_xy: np.ndarray, truth: list[tuple[float, float, float, float]], sigma: float, seed: int
) -> Survey:
    """Readings of transmitters ``truth`` = [(x, y, A, B)] at every scan, noisy, censored."""
    rng = np.random.default_rng(seed)
    scans, txs, rssis = [], [], []
    for tx, (x, y, a, b) in enumerate(truth):
        r = distances(np.array([x, y]), scan_xy, DZ)
        # rssi = A - B ln r + ε, ε ~ N(0, σ²); the phone reports nothing below -95 dBm
        rssi = expected_rssi(r, a, b) + rng.normal(0.0, sigma, r.size)
        heard = np.flatnonzero(rssi >= SENSITIVITY)
        scans.append(heard)
        txs.append(np.full(heard.size, tx))
        rssis.append(np.round(rssi[heard]))
    scan = np.concatenate(scans)
    order = np.lexsort((np.concatenate(txs), scan))
    n = scan_xy.shape[0]
    return Survey(
        scan_t=np.arange(n, dtype=np.int64) * 2000,
        scan_xy=scan_xy,
        scan_floor=np.zeros(n, dtype=np.int32),
        scan_walk=np.zeros(n, dtype=np.int32),
        reading_scan=scan[order].astype(np.int32),
        reading_tx=np.concatenate(txs)[order].astype(np.int32),
        reading_rssi=np.concatenate(rssis)[order].astype(float),
    )


TRUTH = [(14.0, 9.0, -50.0, 16.0), (31.0, 17.0, -42.0, 13.0)]
"""Two transmitters: (x, y, A, B). With B = 16 the first is censored beyond about 16 m."""


def test_position_and_path_loss_are_recovered_despite_censoring() -> None:
    survey = _survey(_walk_grid(), TRUTH, sigma=4.0, seed=7)
    fits = calibrate(survey, PARAMS)
    assert [f.tx for f in fits] == [0, 1]
    for fit, (x, y, a, b) in zip(fits, TRUTH, strict=True):
        assert fit.plausible and fit.converged and not fit.position_known
        # ~500 readings at σ = 4 dB: position within 1 m, A within 1.5 dB, B within 0.8
        assert np.hypot(fit.x - x, fit.y - y) < 1.0, (fit.x, fit.y)
        assert fit.A == pytest.approx(a, abs=1.5)
        assert fit.B == pytest.approx(b, abs=0.8)
        assert fit.sigma == pytest.approx(4.0, abs=0.6)
        assert fit.floor == 0 and fit.z == PARAMS.tx_height_m


def test_censored_scans_remove_the_slope_bias_of_heard_readings_alone() -> None:
    survey = _survey(_walk_grid(), TRUTH[:1], sigma=6.0, seed=11)
    x, y, a, b = TRUTH[0]
    heard = survey.reading_scan
    silent = np.setdiff1d(np.arange(survey.n_scans), heard)
    xy, rssi = survey.scan_xy[heard], survey.reading_rssi
    position = np.array([x, y])
    naive = fit_path_loss(xy, rssi, PARAMS, position=position)
    censored = fit_path_loss(
        xy, rssi, PARAMS, censored_xy=survey.scan_xy[silent], position=position
    )
    # only the lucky strong readings survive far away: without them B comes out flatter
    assert naive.B < b - 1.0
    assert abs(censored.B - b) < abs(naive.B - b)
    assert censored.B == pytest.approx(b, abs=1.0) and censored.A == pytest.approx(a, abs=2.0)


def test_known_position_is_kept_and_only_path_loss_fitted() -> None:
    survey = _survey(_walk_grid(), TRUTH, sigma=3.0, seed=5)
    x, y, a, b = TRUTH[1]
    fits = calibrate(survey, PARAMS, known={1: (0, x, y, PARAMS.tx_height_m)})
    fit = fits[1]
    assert fit.position_known and (fit.x, fit.y) == (x, y)
    assert fit.A == pytest.approx(a, abs=1.0) and fit.B == pytest.approx(b, abs=0.5)
    assert not fits[0].position_known


def test_exact_readings_give_exact_parameters() -> None:
    scan_xy = _walk_grid()
    x, y, a, b = TRUTH[1]
    rssi = expected_rssi(distances(np.array([x, y]), scan_xy, DZ), a, b)
    fit = fit_path_loss(scan_xy, rssi, PARAMS)
    assert fit.xy == pytest.approx([x, y], abs=1e-3)
    assert (fit.A, fit.B) == pytest.approx((a, b), abs=1e-3)
    assert fit.sigma == PARAMS.sigma_min_db


def test_floor_is_where_the_strongest_readings_are() -> None:
    floors = np.array([0] * 30 + [1] * 30 + [2] * 3)
    rssi = np.concatenate([np.full(30, -80.0), np.full(30, -60.0), np.full(3, -30.0)])
    # floor 2 is strongest but has fewer than min_readings readings
    assert transmitter_floor(floors, rssi, PARAMS) == 1


def test_too_few_readings_or_too_little_spread_are_not_fitted() -> None:
    scan_xy = np.array([[5.0, 5.0]] * 40 + [[6.0, 5.0]] * 5)
    survey = _survey(scan_xy, TRUTH[:1], sigma=1.0, seed=1)
    assert calibrate(survey, PARAMS) == []


@pytest.mark.parametrize("known", [False, True])
def test_analytic_jacobian_matches_finite_differences(known: bool) -> None:
    rng = np.random.default_rng(3)
    xy = rng.uniform(0.0, 30.0, (40, 2))
    # some readings saturated, some heard, plus censored scans
    rssi = np.concatenate([np.full(5, -20.0), rng.uniform(-95.0, -40.0, 35)])
    censored = rng.uniform(0.0, 30.0, (25, 2))
    theta = np.array([-45.0, 14.0]) if known else np.array([12.0, 9.0, -45.0, 14.0])
    position = np.array([12.0, 9.0]) if known else None
    args = (xy, rssi, censored, 5.0, DZ, position, PARAMS)
    analytic = _jacobian(theta, *args)
    numeric = approx_derivative(_residuals, theta, method="3-point", args=args)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-7)
