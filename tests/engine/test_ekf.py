"""The UWB + inertial EKF (Brovko): process model, update, gating, start-up, simulated gain."""

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
from app.engine.plan import FloorPlan
from app.engine.samples import Fixes, ImuSamples
from app.engine.site import Floor, SiteModel
from app.engine.uwb_tracker import UwbTracker, UwbTrackerParams
from tests.engine.tag_sim import T0, run, turning_walk


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
    (Brovko's report claims about 1/5), 1/2 with the course from motion alone."""
    t, xy, rate = turning_walk(seed=5)
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
    out = run(tracker, int(t[-1]), **parts)
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
