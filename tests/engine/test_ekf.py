"""Seed 001 EKF and the UWB / locator trackers: model, update, simulated gain, biases, state."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.ekf import (
    POSITION_H,
    EkfParams,
    PositionEkf,
    ekf_update,
    heading_deg,
    imu_yaw_rate,
    process_jacobian,
    propagate,
)
from app.engine.lateration.solver import solve
from app.engine.locator_tracker import (
    LocatorTracker,
    LocatorTrackerParams,
    strongest_centroid,
    window_means,
)
from app.engine.plan import FloorPlan, burn_segments
from app.engine.samples import Batch, Fixes, ImuSamples, Ranges, RssiReadings
from app.engine.site import Emitters, Floor, SiteModel
from app.engine.uwb_bias import (
    BiasParams,
    accumulate,
    residual_projector,
    solve_biases,
    survey_biases,
)
from app.engine.uwb_tracker import UwbTracker, UwbTrackerParams, group_epochs
from app.workers.snapshots import decode, encode

T0 = 1_700_000_000_000
ANCHORS = np.array(
    [
        [-4.0, 3.0, 2.2],
        [0.0, 3.2, 2.4],
        [4.0, 3.0, 2.1],
        [4.2, 0.0, 2.5],
        [4.0, -3.0, 2.3],
        [0.0, -3.1, 2.2],
        [-4.0, -3.0, 2.4],
        [-4.1, 0.0, 2.0],
    ]
)


def _site(free: np.ndarray | None = None, anchors: np.ndarray = ANCHORS) -> SiteModel:
    free = np.ones((160, 200), bool) if free is None else free
    plan = FloorPlan.from_raster(origin=np.array([-10.0, -8.0]), cell=0.1, free=free)
    n = len(anchors)
    table = Emitters(
        ids=tuple(f"a{i}" for i in range(n)),
        floor=np.zeros(n, np.int32),
        xyz=anchors,
        A=np.full(n, -60.0),
        B=np.full(n, 8.0),
        sigma=np.full(n, 4.0),
    )
    return SiteModel("s", (Floor("F", 0, 4.0, plan),), anchors=table, locators=table)


def _walk(seed: int, seconds: float = 120.0, dt: float = 0.02, speed: float = 1.2):
    """A walk turning at a random constant rate (±0.4 rad/s) for 5 s at a time."""
    rng = np.random.default_rng(seed)
    n = int(seconds / dt)
    t = np.arange(n) * dt
    rate = np.repeat(rng.uniform(-0.4, 0.4, n // 250 + 1), 250)[:n]
    course = np.cumsum(rate) * dt
    v = speed + 0.1 * np.sin(0.3 * t)
    xy = np.column_stack([np.cumsum(v * np.cos(course)), np.cumsum(v * np.sin(course))]) * dt
    return (T0 + np.round(t * 1000)).astype(np.int64), xy, rate


def _slice_batch(lo: int, hi: int, **parts) -> Batch:
    """Samples with lo <= t < hi of each part (Fixes, ImuSamples, Ranges, RssiReadings)."""
    out = {}
    for name, arr in parts.items():
        sel = (arr.t >= lo) & (arr.t < hi)
        fields = {k: getattr(arr, k)[sel] for k in arr.__dataclass_fields__}
        out[name] = type(arr)(**fields)
    return Batch(**out)


def _run(tracker, t_end: int, step: int = 1000, **parts):
    out = []
    start = min(int(p.t.min()) for p in parts.values())
    for lo in range(start, t_end + step, step):
        out += tracker.process(_slice_batch(lo, lo + step, **parts))
    return out


def test_process_model_and_its_jacobian() -> None:
    """Eq. 3 moves along the course; eq. 9 is its derivative (central differences)."""
    x = np.array([1.0, 2.0, 1.5, 0.7])
    moved = propagate(x, 0.5, 0.2, 0.0)
    np.testing.assert_allclose(moved, [1 + 0.75 * np.cos(0.7), 2 + 0.75 * np.sin(0.7), 1.5, 0.8])
    assert propagate(x, 0.5, 0.0, 0.4)[3] == pytest.approx(0.7 * (1 - 0.2))
    F = process_jacobian(x, 0.5, 0.4)
    for k in range(4):
        h = np.zeros(4)
        h[k] = 1e-6
        column = (propagate(x + h, 0.5, 0.2, 0.4) - propagate(x - h, 0.5, 0.2, 0.4)) / 2e-6
        np.testing.assert_allclose(F[:, k], column, atol=1e-8)


def test_joseph_update_equals_the_textbook_form_and_gates() -> None:
    rng = np.random.default_rng(1)
    L = rng.normal(size=(4, 4))
    P = L @ L.T + np.eye(4)
    x = rng.normal(size=4)
    R = np.diag([0.3, 0.5])
    z = x[:2] + np.array([0.4, -0.2])
    x1, P1, d2, ok = ekf_update(x, P, z, R, POSITION_H, gate=1e9)
    S = POSITION_H @ P @ POSITION_H.T + R
    K = P @ POSITION_H.T @ np.linalg.inv(S)
    assert ok
    np.testing.assert_allclose(x1, x + K @ (z - x[:2]))
    np.testing.assert_allclose(P1, (np.eye(4) - K @ POSITION_H) @ P, atol=1e-12)
    assert d2 == pytest.approx((z - x[:2]) @ np.linalg.inv(S) @ (z - x[:2]))
    x2, P2, _, rejected = ekf_update(x, P, x[:2] + 50.0, R, POSITION_H, EkfParams().gate)
    assert not rejected and x2 is x and P2 is P
    assert EkfParams(gate_probability=0.99).gate == pytest.approx(-2 * np.log(0.01))


def test_headings_and_yaw_rate() -> None:
    assert heading_deg(0.0) == pytest.approx(90.0)  # course east
    assert heading_deg(np.pi / 2) == pytest.approx(0.0)  # north
    assert heading_deg(np.pi) == pytest.approx(270.0)
    gyro = np.array([[0.0, 0.0, 0.3], [0.3, 0.0, 0.0], [0.1, 0.2, 0.3]])
    acc = np.array([[0.0, 0.0, 9.8], [9.8, 0.0, 0.0], [np.nan, np.nan, np.nan]])
    np.testing.assert_allclose(imu_yaw_rate(acc, gyro), [0.3, 0.3, 0.3])


@pytest.mark.parametrize(("gyro", "limit"), [(True, 1 / 3), (False, 1 / 2)])
def test_filter_beats_raw_fixes_in_simulation(gyro: bool, limit: float) -> None:
    """Fixes at 10 Hz with σ = 0.3 m: RMS at most 1/3 of the fixes' with a gyro
    (seed 001 claims about 1/5), 1/2 with the course from motion alone."""
    t, xy, rate = _walk(seed=5)
    rng = np.random.default_rng(6)
    idx = np.arange(0, t.size, 5)
    noisy = xy[idx] + rng.normal(0.0, 0.3, (idx.size, 2))
    fixes = Fixes(
        t=t[idx],
        xyz=np.column_stack([noisy, np.ones(idx.size)]),
        floor=np.zeros(idx.size, np.int32),
        std=np.full(idx.size, 0.3),
    )
    parts: dict = {"fixes": fixes}
    ekf = EkfParams(accel_noise=0.05, turn_noise_gyro=0.02, position_noise=0.0)
    if gyro:
        parts["imu"] = ImuSamples(
            t=t,
            acc=np.tile([0.0, 0.0, 9.81], (t.size, 1)),
            gyro=np.column_stack(
                [np.zeros((t.size, 2)), rate + 0.01 + rng.normal(0, 0.02, t.size)]
            ),
            mag=np.full((t.size, 3), np.nan),
            rot=np.full((t.size, 4), np.nan),
        )
    plan = FloorPlan.from_raster(
        origin=np.array([-500.0, -500.0]), cell=1.0, free=np.ones((1000, 1000), bool)
    )
    site = SiteModel("s", (Floor("F", 0, 4.0, plan),))
    tracker = UwbTracker(site, UwbTrackerParams(ekf=ekf, emit_every_ms=0))
    out = _run(tracker, int(t[-1]), **parts)
    et = np.array([e.t for e in out])
    est = np.array([[e.x, e.y] for e in out])
    truth = np.column_stack([np.interp(et, t, xy[:, 0]), np.interp(et, t, xy[:, 1])])
    settled = et > T0 + 5000
    ekf_rms = np.sqrt(np.mean(np.sum((est[settled] - truth[settled]) ** 2, axis=1)))
    raw_rms = np.sqrt(np.mean(np.sum((noisy - xy[idx]) ** 2, axis=1)))
    assert len(out) > 0.97 * idx.size
    assert ekf_rms <= limit * raw_rms
    moving = [e for e in out if e.t > T0 + 5000]
    assert all(np.isfinite(e.heading) and e.speed > 0.5 for e in moving)


def test_gate_and_restart_after_a_run_of_rejected_fixes() -> None:
    ekf = PositionEkf(EkfParams(max_rejections=3))
    R = np.eye(2) * 0.01
    for k in range(12):
        assert ekf.update(T0 + 100 * k, np.array([0.1 * k, 0.0]), R)
    assert ekf.moving
    assert not ekf.update(T0 + 1200, np.array([20.0, 5.0]), R)
    assert not ekf.update(T0 + 1300, np.array([20.0, 5.0]), R)
    assert ekf.update(T0 + 1400, np.array([20.0, 5.0]), R)  # third rejection: start over there
    np.testing.assert_allclose(ekf.x[:2], [20.0, 5.0])
    assert not ekf.moving and ekf.rejections == 0


def test_course_and_speed_start_from_the_first_displacement() -> None:
    ekf = PositionEkf(EkfParams(init_distance_m=0.5))
    R = np.eye(2) * 1e-4
    for k in range(11):
        ekf.update(T0 + 100 * k, np.array([0.0, 0.1 * k]), R)
    assert ekf.moving
    assert ekf.x[3] == pytest.approx(np.pi / 2, abs=0.05)
    assert ekf.x[2] == pytest.approx(1.0, rel=0.1)
    _, _, heading, accuracy, speed = ekf.estimate()
    assert heading == pytest.approx(0.0, abs=3.0) or heading == pytest.approx(360.0, abs=3.0)
    assert accuracy > 0 and speed == pytest.approx(ekf.x[2])


def test_epochs_split_at_repeated_anchors_and_gaps() -> None:
    t = np.array([0, 0, 0, 10, 10, 50, 51, 52], dtype=np.int64)
    anchor = np.array([0, 1, 2, 0, 1, 2, 2, 3])
    epochs = group_epochs(t, anchor, np.arange(8.0), np.ones(8), epoch_ms=30)
    assert [e.anchors.tolist() for e in epochs] == [[0, 1, 2], [0, 1], [2], [2, 3]]
    assert [e.t for e in epochs] == [0, 10, 50, 52]


def _ranges(t: np.ndarray, xy: np.ndarray, bias: np.ndarray, rng, every: int = 5) -> Ranges:
    idx = np.arange(0, t.size, every)
    pos = np.column_stack([xy[idx], np.full(idx.size, 1.0)])
    d = (
        np.linalg.norm(pos[:, None] - ANCHORS[None], axis=-1)
        + bias
        + rng.normal(0, 0.05, (idx.size, 8))
    )
    return Ranges(
        t=np.repeat(t[idx], 8),
        anchor=np.tile(np.arange(8, dtype=np.int32), idx.size),
        range=d.ravel(),
        std=np.full(d.size, 0.1),
    )


def _room_walk(seed: int, seconds: float = 60.0):
    """A tag circling inside the anchors' room at 0.5 m/s on a wobbling radius."""
    t = np.arange(0, seconds, 0.02)
    r = 2.0 + 0.8 * np.sin(0.23 * t + seed)
    a = 0.25 * t
    xy = np.column_stack([r * np.cos(a), 0.8 * r * np.sin(a)])
    return (T0 + np.round(t * 1000)).astype(np.int64), xy


def test_self_calibration_recovers_range_biases_without_truth() -> None:
    """Biases U(0.1, 0.3) m on 8 anchors (two more anchors of the site never heard, ranges
    listed in reverse anchor order): learnt within 2 cm RMS, halving the position error."""
    rng = np.random.default_rng(42)
    bias = rng.uniform(0.1, 0.3, 8)
    t, xy = _room_walk(0)
    ranges = _ranges(t, xy, bias, rng)
    order = np.lexsort((-ranges.anchor, ranges.t))
    ranges = Ranges(*(getattr(ranges, k)[order] for k in ("t", "anchor", "range", "std")))
    site = _site(anchors=np.vstack([ANCHORS, [[9.0, 7.0, 2.0], [-9.0, 7.0, 2.0]]]))
    errors = {}
    for learn in (False, True):
        tracker = UwbTracker(site, UwbTrackerParams(self_calibrate=learn, emit_every_ms=0))
        out = _run(tracker, int(t[-1]), ranges=ranges)
        late = [e for e in out if e.t > T0 + 30_000]
        est = np.array([[e.x, e.y] for e in late])
        et = np.array([e.t for e in late])
        truth = np.column_stack([np.interp(et, t, xy[:, 0]), np.interp(et, t, xy[:, 1])])
        errors[learn] = np.sqrt(np.mean(np.sum((est - truth) ** 2, axis=1)))
        if learn:
            assert np.sqrt(np.mean((tracker.bias[:8] - bias) ** 2)) < 0.02
            assert (tracker.bias[8:] == 0).all() and sorted(tracker.bias_ids) == list(range(8))
            assert tracker.bias_S.shape == (8, 8)
    assert errors[True] < 0.5 * errors[False]


def test_bias_equations_by_hand() -> None:
    """One fix: S gets I − P on the fix's anchors, g the residuals plus (I − P) b̂."""
    anchors = ANCHORS[:5]
    position = np.array([0.5, 0.2, 1.0])
    M = residual_projector(anchors, position, 2)
    np.testing.assert_allclose(M @ M, M, atol=1e-12)  # a projector
    assert np.trace(M) == pytest.approx(3.0)  # 5 readings − 2 unknowns
    S, g = accumulate(
        np.eye(8),
        np.ones(8),
        np.full(8, 0.1),
        np.arange(5),
        ANCHORS,
        position,
        np.array([0.01, -0.02, 0.0, 0.03, -0.01]),
        np.ones(5),
        0.5,
        2,
    )
    np.testing.assert_allclose(S[:5, :5], 0.5 * np.eye(5) + M)
    np.testing.assert_allclose(S[5:, 5:], 0.5 * np.eye(3))
    np.testing.assert_allclose(
        g[:5], 0.5 + np.array([0.01, -0.02, 0.0, 0.03, -0.01]) + M @ np.full(5, 0.1)
    )
    skipped, _ = accumulate(
        S, g, np.zeros(8), np.arange(3), ANCHORS, position, np.zeros(3), np.ones(3), 1.0, 2
    )
    np.testing.assert_array_equal(skipped, S)  # 3 readings: below min_readings
    prior = np.full(8, 0.2)
    np.testing.assert_allclose(solve_biases(np.zeros((8, 8)), np.zeros(8), prior), prior)
    b = solve_biases(np.eye(8) * 1e6, np.full(8, 5e5), prior, BiasParams(max_abs_m=0.3))
    np.testing.assert_allclose(b, 0.3)


def test_survey_biases_are_medians_of_range_errors() -> None:
    truth = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 1.0, 1.0]])
    d = np.linalg.norm(truth[:, None] - ANCHORS[None, :3], axis=-1)
    ranges = d + np.array([[0.1, 0.2, np.nan], [0.3, 0.2, np.nan], [0.2, 0.2, np.nan]])
    s = survey_biases(ANCHORS[:3], ranges, truth)
    np.testing.assert_allclose(s.bias[:2], [0.2, 0.2])
    assert np.isnan(s.bias[2]) and s.count.tolist() == [3, 3, 0]


def test_snapshot_round_trip_continues_identically() -> None:
    rng = np.random.default_rng(3)
    t, xy = _room_walk(1, seconds=20.0)
    ranges = _ranges(t, xy, rng.uniform(0.1, 0.3, 8), rng)
    params = UwbTrackerParams(emit_every_ms=100)
    whole = UwbTracker(_site(), params)
    first = _run(whole, int(t[-1]), ranges=ranges)
    half = UwbTracker(_site(), params)
    mid = T0 + 10_000
    out = _run(half, mid - 1000, ranges=ranges)
    restored = UwbTracker.from_snapshot(_site(), params, decode(encode(half.snapshot())))
    for lo in range(mid, int(t[-1]) + 1000, 1000):
        out += restored.process(_slice_batch(lo, lo + 1000, ranges=ranges))
    assert [(e.t, e.x, e.y) for e in out] == [(e.t, e.x, e.y) for e in first]
    assert np.all(np.diff([e.t for e in first]) >= 100)


def test_given_fixes_are_projected_off_walls() -> None:
    free = np.ones((160, 200), bool)
    burn_segments(free, np.array([[0.0, -8.0, 0.0, 8.0]]), origin=np.array([-10.0, -8.0]), cell=0.1)
    site = _site(free)
    tracker = UwbTracker(site, UwbTrackerParams(emit_every_ms=0))
    fix = Fixes(
        t=np.array([T0], np.int64),
        xyz=np.array([[0.02, 1.0, 1.2]]),
        floor=np.zeros(1, np.int32),
        std=np.array([0.2]),
    )
    (est,) = tracker.process(Batch(fixes=fix))
    plan = site.floors[0].plan
    assert not plan.is_free(np.array([0.02, 1.0]))
    assert plan.is_free(np.array([est.x, est.y]))
    assert np.hypot(est.x - 0.02, est.y - 1.0) < 0.15
    assert est.z == pytest.approx(1.2) and est.method == "ekf"
    assert est.accuracy == pytest.approx(np.sqrt(-2 * np.log(0.32)) * 0.2)


def test_window_means_agree_with_a_loop() -> None:
    rng = np.random.default_rng(9)
    t = np.sort(rng.integers(0, 10_000, 300))
    tx = rng.integers(0, 5, 300)
    rssi = rng.normal(-70, 5, 300)
    times = np.arange(500, 10_001, 500)
    mean, count = window_means(t, tx, rssi, 5, times, 2000)
    for i, tau in enumerate(times):
        for k in range(5):
            sel = (t > tau - 2000) & (t <= tau) & (tx == k)
            assert count[i, k] == sel.sum()
            if sel.any():
                assert mean[i, k] == pytest.approx(rssi[sel].mean())
            else:
                assert np.isnan(mean[i, k])


def test_locator_tracker_follows_a_simulated_tag() -> None:
    """Readings every 0.5 s per locator from rssi = A − B ln d + N(0, 4 dB): the tracker stays
    within 20 % of the RMS of its own unfiltered fixes (RSSI fixes from overlapping windows are
    correlated and heavy-tailed: the filter smooths little) and restores from a snapshot."""
    rng = np.random.default_rng(12)
    t, xy = _room_walk(2, seconds=60.0)
    site = _site()
    loc = site.locators
    idx = np.arange(0, t.size, 25)
    pos = np.column_stack([xy[idx], np.full(idx.size, 1.0)])
    d = np.linalg.norm(pos[:, None] - loc.xyz[None], axis=-1)
    rssi = loc.A - loc.B * np.log(d) + rng.normal(0, 4.0, d.shape)
    readings = RssiReadings(
        t=np.repeat(t[idx], 8) + np.tile(np.arange(8), idx.size),
        tx=np.tile(np.arange(8, dtype=np.int32), idx.size),
        rssi=rssi.ravel(),
    )
    params = LocatorTrackerParams(tag_height_m=1.0, fix_std_floor_m=0.3)
    tracker = LocatorTracker(site, params)
    out = _run(tracker, int(t[-1]), rssi=readings)
    et = np.array([e.t for e in out])
    assert np.all(et % params.step_ms == 0) and et.size > 0.9 * 60_000 / params.step_ms

    def rms(times: np.ndarray, est: np.ndarray) -> float:
        truth = np.column_stack([np.interp(times, t, xy[:, 0]), np.interp(times, t, xy[:, 1])])
        return float(np.sqrt(np.mean(np.sum((est - truth) ** 2, axis=1))))

    mean, count = window_means(readings.t, readings.tx, readings.rssi, 8, et, params.window_ms)
    x0 = strongest_centroid(mean, loc.xyz)
    x0[:, 2] = 1.0
    raw = solve(
        "rssi",
        loc.xyz,
        mean,
        loc.sigma[None, :] / np.sqrt(np.clip(count, 1, params.max_samples)),
        A=loc.A,
        B=loc.B,
        height=1.0,
        dims=2,
        x0=x0,
    )
    raw_rms = rms(et[raw.ok], raw.position[raw.ok, :2])
    assert raw_rms < 1.5
    assert rms(et, np.array([[e.x, e.y] for e in out])) < 1.2 * raw_rms
    restored = LocatorTracker.from_snapshot(site, params, decode(encode(tracker.snapshot())))
    assert restored.next_fix == tracker.next_fix and restored.t.size == tracker.t.size
