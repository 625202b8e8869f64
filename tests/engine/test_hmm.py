"""The fingerprint + inertial HMM on small synthetic radio maps with a known answer: step
displacement, transition on the grid, position and floor from scans, snapshot and resume."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import signal

from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.kernels import propagate
from app.engine.hmm.params import HmmParams
from app.engine.hmm.tracker import HmmTracker
from app.engine.hmm.transition import step_displacement, transition_kernel
from app.engine.radiomap import RadioMap
from app.engine.samples import Batch, RssiReadings
from app.workers import snapshots

SLOPE_DB = 3.0
"""RSSI change per metre along the synthetic corridor."""


def corridor(floor: int, tx: tuple[int, int], n: int = 30) -> RadioMap:
    """A 1 × n m corridor of 1 m cells; transmitter tx[0] at its west end, tx[1] at its east."""
    c = np.arange(n)
    mean = np.stack([-40.0 - SLOPE_DB * c, -40.0 - SLOPE_DB * (n - 1 - c)], axis=1)
    return RadioMap(
        floor=floor,
        cell=1.0,
        origin=np.zeros(2),
        shape=(1, n),
        ij=np.stack([np.zeros(n), c], axis=1).astype(np.int32),
        tx=np.array(tx, dtype=np.int32),
        mean=mean.astype(np.float32),
        var=np.full((n, 2), 4.0, dtype=np.float32),
        detect=np.full((n, 2), 0.99, dtype=np.float32),
        weight=np.ones(n, dtype=np.float32),
    )


def scan_at(t: int, cell: int, tx: tuple[int, int], n: int = 30) -> Batch:
    """A noise-free scan taken in corridor cell ``cell``."""
    rssi = [-40.0 - SLOPE_DB * cell, -40.0 - SLOPE_DB * (n - 1 - cell)]
    return Batch(
        rssi=RssiReadings(
            t=np.array([t, t], dtype=np.int64),
            tx=np.array(tx, dtype=np.int32),
            rssi=np.array(rssi),
        )
    )


def test_a_step_moves_along_its_heading_with_along_and_across_track_variance() -> None:
    d, cov = step_displacement(0.7, 90.0, 0.1, 10.0)
    # a step east: D = (0.7, 0); along x σ_d², across (L σ_φ)²
    assert d == pytest.approx([0.7, 0.0], abs=1e-12)
    assert cov == pytest.approx(np.diag([0.01, (0.7 * np.radians(10.0)) ** 2]), abs=1e-12)
    # north-east: the two variances rotate with the step, the trace stays their sum
    d, cov = step_displacement(1.0, 45.0, 0.1, 10.0)
    assert d == pytest.approx([np.sqrt(0.5), np.sqrt(0.5)], abs=1e-12)
    assert np.trace(cov) == pytest.approx(0.01 + np.radians(10.0) ** 2, abs=1e-12)
    assert cov[0, 1] == pytest.approx(0.5 * (0.01 - np.radians(10.0) ** 2), abs=1e-12)
    # no heading: no move, the length spread every way
    d, cov = step_displacement(0.7, float("nan"), 0.1, 10.0)
    assert d == pytest.approx([0.0, 0.0]) and cov == pytest.approx(np.eye(2) * 0.25)


def test_transition_moves_the_mass_by_the_displacement() -> None:
    m = corridor(0, (0, 1), n=10)
    prob = np.zeros(10)
    prob[3] = 1.0
    kernel, h = transition_kernel(np.array([2.0, 0.0]), np.eye(2) * 0.05, 1.0, 3.0)
    out = propagate(prob, m.ij, m.index_grid(), kernel, h)
    assert int(np.argmax(out)) == 5
    # the row above and below are not reference points: their share of the kernel is lost
    assert out.sum() == pytest.approx(kernel[h].sum(), rel=1e-9)


def test_the_compiled_transition_is_the_grid_convolution_restricted_to_points() -> None:
    # an L-shaped floor: a 12 x 3 m corridor and a 3 x 10 m one, 1 m cells
    mask = np.zeros((12, 14), dtype=bool)
    mask[0:3, :12] = True
    mask[:, 9:12] = True
    ij = np.argwhere(mask).astype(np.int32)
    grid = np.full(mask.shape, -1, dtype=np.int32)
    grid[ij[:, 0], ij[:, 1]] = np.arange(ij.shape[0])
    rng = np.random.default_rng(4)
    prob = np.where(rng.random(ij.shape[0]) < 0.3, rng.random(ij.shape[0]), 0.0)
    kernel, h = transition_kernel(np.array([1.3, -0.6]), np.diag([0.4, 0.9]), 1.0, 3.0)
    out = propagate(prob, ij, grid, kernel, h)
    # the same move as an image convolution: every cell, then read at the points
    image = np.zeros(mask.shape)
    image[ij[:, 0], ij[:, 1]] = prob
    moved = signal.convolve2d(image, kernel, mode="same")
    assert out == pytest.approx(moved[ij[:, 0], ij[:, 1]], abs=1e-15)
    # mass moved off the floor is lost, none is made
    assert out.sum() < prob.sum()


def test_a_still_device_is_located_in_its_cell() -> None:
    model = EmissionModel([corridor(0, (0, 1))], HmmParams())
    tracker = HmmTracker(model, HmmParams())
    estimates = []
    for k in range(8):
        estimates += tracker.process(scan_at(1000 * k, 12, (0, 1)))
    assert estimates and all(e.method == "hmm" and e.floor == 0 for e in estimates)
    last = estimates[-1]
    # cell 12 has its centre at x = 12.5, y = 0.5
    assert (last.x, last.y) == pytest.approx((12.5, 0.5), abs=0.5)
    assert last.accuracy >= HmmParams().min_accuracy_m


def test_the_radius_is_scaled_then_floored_as_the_build_calibrated_it() -> None:
    def last_accuracy(params: HmmParams) -> float:
        tracker = HmmTracker(EmissionModel([corridor(0, (0, 1))], params), params)
        estimates = [e for k in range(8) for e in tracker.process(scan_at(1000 * k, 12, (0, 1)))]
        return estimates[-1].accuracy

    wide = HmmParams(min_accuracy_m=0.1, walk_noise_m2_per_s=5.0)
    radius = last_accuracy(wide)
    assert radius > 0.5
    assert last_accuracy(replace(wide, radius_scale=0.5)) == pytest.approx(0.5 * radius)
    assert last_accuracy(replace(wide, radius_scale=0.5, accuracy_floor_m=3.0)) == pytest.approx(
        np.hypot(0.5 * radius, 3.0)
    )
    # never below the smallest radius the grid allows
    assert last_accuracy(replace(wide, radius_scale=1e-6)) == pytest.approx(0.1)


def test_the_match_factor_follows_the_scans_with_its_time_constant() -> None:
    params = HmmParams(radius_match_tau_s=30.0)
    tracker = HmmTracker(EmissionModel([corridor(0, (0, 1))], params), params)
    # the first scan sets it
    tracker._follow_match(5000, 2.0)
    assert tracker.match == 2.0
    tracker.t_scan = 5000
    # 30 s later a scan matching at 4 moves it 1 - 1/e of the way there
    tracker._follow_match(35_000, 4.0)
    assert tracker.match == pytest.approx(2.0 + (1.0 - np.exp(-1.0)) * 2.0)
    without = HmmTracker(
        EmissionModel([corridor(0, (0, 1))], params), replace(params, radius_match_tau_s=0.0)
    )
    without.t_scan = 5000
    without._follow_match(6000, 4.0)
    assert without.match == 4.0


def test_the_floor_is_the_one_whose_map_explains_the_scan() -> None:
    model = EmissionModel([corridor(0, (0, 1)), corridor(1, (2, 3))], HmmParams())
    tracker = HmmTracker(model, HmmParams())
    estimates = []
    for k in range(3):
        estimates += tracker.process(scan_at(1000 * k, 20, (2, 3)))
    assert {e.floor for e in estimates} == {1}
    assert estimates[-1].x == pytest.approx(20.5, abs=0.5)


def test_snapshot_and_resume_give_the_same_estimates() -> None:
    model = EmissionModel([corridor(0, (0, 1))], HmmParams())
    batches = [scan_at(1000 * k, 5 + k // 2, (0, 1)) for k in range(12)]
    straight = HmmTracker(model, HmmParams())
    expected = [e for b in batches for e in straight.process(b)]
    first = HmmTracker(model, HmmParams())
    got = [e for b in batches[:6] for e in first.process(b)]
    # through the workers' serialisation: plain arrays and numbers only
    state = snapshots.decode(snapshots.encode({"s": first.snapshot()}))["s"]
    resumed = HmmTracker.from_snapshot(model, HmmParams(), state)
    got += [e for b in batches[6:] for e in resumed.process(b)]
    assert len(got) == len(expected) > 6
    fields = ("t", "x", "y", "z", "floor", "heading", "accuracy", "speed")
    # assert_array_equal counts NaN (unknown heading and speed) as equal to NaN
    np.testing.assert_array_equal(
        [[getattr(e, f) for f in fields] for e in got],
        [[getattr(e, f) for f in fields] for e in expected],
    )
