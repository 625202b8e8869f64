"""PDR: step counting, the 0.3 s rule, Weinberg length, headings, chunking and snapshots."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from app.datasets import data_dir
from app.datasets.ilc import imu_samples, read_walk
from app.engine.pdr import (
    Pdr,
    PdrParams,
    Steps,
    detect_steps,
    weinberg_length,
)
from app.engine.pdr_kernel import magnetic_heading, rotation_heading, yaw_rate
from app.engine.samples import ImuSamples

G = 9.80665
WALK = data_dir() / "ilc" / "site1" / "F2" / "path_data_files"


def _rz(theta: float) -> np.ndarray:
    """Rotation matrix about +z (counter-clockwise seen from above), angle in radians."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _walking(
    *,
    cadence_hz: float,
    n_steps: int,
    amplitude: float,
    heading_deg: float = 0.0,
    gyro_bias: float = 0.0,
    rot: bool = True,
    noise: float = 0.05,
    seed: int = 0,
) -> ImuSamples:
    """Flat phone: 3 s standing, n_steps sine cycles of |a| at the cadence, 3 s standing.

    The phone's +y axis points at ``heading_deg``; the field is 20 µT north,
    40 µT down; the gyro reads ``gyro_bias`` rad/s counter-clockwise about z;
    the accelerometer has Gaussian noise of std ``noise`` (m/s²).
    """
    rng = np.random.default_rng(seed)
    walk_s = n_steps / cadence_hz
    t = np.arange(0, int((6.0 + walk_s) * 1000), 20, dtype=np.int64) + 1_600_000_000_000
    s = (t - t[0]) / 1000.0 - 3.0
    walking = (s >= 0) & (s < walk_s)
    # a_z = g + A sin(2π f s) while walking: one peak per cycle, at s = (k + 1/4)/f
    az = G + np.where(walking, amplitude * np.sin(2 * np.pi * cadence_hz * s), 0.0)
    acc = np.column_stack([np.zeros_like(az), np.zeros_like(az), az])
    acc += rng.normal(0.0, noise, acc.shape)
    # The phone turned by θ = -heading about up: the device sees world vectors as R_z(θ)ᵀ v.
    theta = -np.radians(heading_deg)
    mag = np.tile(_rz(theta).T @ np.array([0.0, 20.0, -40.0]), (t.size, 1))
    gyro = np.tile([0.0, 0.0, gyro_bias], (t.size, 1))
    quat = np.tile([0.0, 0.0, np.sin(theta / 2), np.cos(theta / 2)], (t.size, 1))
    return ImuSamples(
        t=t, acc=acc, gyro=gyro, mag=mag, rot=quat if rot else np.full((t.size, 4), np.nan)
    )


def _chunks(imu: ImuSamples, sizes: np.ndarray) -> list[ImuSamples]:
    bounds = np.r_[0, np.cumsum(sizes)]
    bounds = bounds[bounds < len(imu)]
    return [
        ImuSamples(
            t=imu.t[a:b], acc=imu.acc[a:b], gyro=imu.gyro[a:b], mag=imu.mag[a:b], rot=imu.rot[a:b]
        )
        for a, b in zip(bounds, np.r_[bounds[1:], len(imu)], strict=True)
    ]


def _assert_same_steps(a: Steps, b: Steps, heading_atol: float = 0.0) -> None:
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.length, b.length)
    np.testing.assert_array_equal(a.swing, b.swing)
    np.testing.assert_allclose(a.heading, b.heading, rtol=0, atol=heading_atol)


@pytest.mark.parametrize(("cadence_hz", "n_steps"), [(1.5, 12), (1.8, 20), (2.2, 31)])
def test_synthetic_walk_gives_exactly_one_step_per_cycle(cadence_hz: float, n_steps: int) -> None:
    steps = detect_steps(_walking(cadence_hz=cadence_hz, n_steps=n_steps, amplitude=3.0))
    assert len(steps) == n_steps
    # Peaks one period apart: the filter delays them all alike.
    np.testing.assert_allclose(np.diff(steps.t), 1000.0 / cadence_hz, atol=21.0)


def test_standing_still_gives_no_step() -> None:
    assert len(detect_steps(_walking(cadence_hz=1.8, n_steps=0, amplitude=3.0))) == 0


def test_only_the_first_peak_within_tau_counts() -> None:
    # Peaks every 250 ms < τ = 300 ms: every second peak is a step.
    steps = detect_steps(_walking(cadence_hz=4.0, n_steps=40, amplitude=8.0))
    assert len(steps) == 20
    np.testing.assert_allclose(np.diff(steps.t), 500.0, atol=21.0)
    loose = detect_steps(
        _walking(cadence_hz=4.0, n_steps=40, amplitude=8.0),
        replace(PdrParams(), min_step_interval_ms=200),
    )
    assert len(loose) == 40


def test_weinberg_length_on_hand_computed_swings() -> None:
    # 0.5 · 16^(1/4) = 1.0, 0.5 · 81^(1/4) = 1.5, 0.5 · 1 = 0.5
    np.testing.assert_allclose(weinberg_length(np.array([16.0, 81.0, 1.0]), 0.5), [1.0, 1.5, 0.5])


def test_step_length_is_weinberg_of_the_filtered_swing() -> None:
    params = PdrParams()
    steps = detect_steps(_walking(cadence_hz=1.8, n_steps=20, amplitude=3.0), params)
    np.testing.assert_allclose(steps.length, params.weinberg_k * steps.swing**0.25, rtol=1e-15)
    # Butterworth gain at 1.8 Hz with a 2.5 Hz cut-off: 1 / sqrt(1 + (1.8/2.5)^4); swing = 2 A gain.
    gain = 1.0 / np.sqrt(1.0 + (1.8 / 2.5) ** 4)
    np.testing.assert_allclose(np.median(steps.swing), 2 * 3.0 * gain, rtol=0.03)


@pytest.mark.parametrize(
    ("theta_deg", "heading"), [(0.0, 0.0), (-90.0, 90.0), (180.0, 180.0), (90.0, 270.0)]
)
def test_rotation_vector_heading_of_a_flat_phone(theta_deg: float, heading: float) -> None:
    # q = (0, 0, sin θ/2, cos θ/2): the phone turned by θ counter-clockwise about up.
    half = np.radians(theta_deg) / 2
    got4 = rotation_heading(0.0, 0.0, np.sin(half), np.cos(half))
    got3 = rotation_heading(0.0, 0.0, np.sin(half), np.nan)
    for got in (got4, got3):
        assert min(abs(got - heading), 360 - abs(got - heading)) < 1e-9


def test_rotation_vector_heading_ignores_pitch() -> None:
    # q = q_z(θ) ⊗ q_x(φ): pitched up 30° about the device x axis, then turned by θ = 40°.
    tz, px = np.radians(40.0) / 2, np.radians(30.0) / 2
    got = rotation_heading(
        np.cos(tz) * np.sin(px),
        np.sin(tz) * np.sin(px),
        np.sin(tz) * np.cos(px),
        np.cos(tz) * np.cos(px),
    )
    assert got == pytest.approx(320.0, abs=1e-9)


@pytest.mark.parametrize("heading", [0.0, 45.0, 135.0, 270.0])
def test_magnetic_heading_of_a_flat_phone(heading: float) -> None:
    theta = -np.radians(heading)
    mag = _rz(theta).T @ np.array([0.0, 20.0, -40.0])
    got = magnetic_heading(0.0, 0.0, G, *mag)
    assert min(abs(got - heading), 360 - abs(got - heading)) < 1e-9


def test_yaw_rate_is_clockwise_about_up() -> None:
    # the phone face up, then face down, turning counter-clockwise about its own z
    assert yaw_rate(0.0, 0.0, G, 0.1, 0.2, 0.5) == pytest.approx(-0.5)
    assert yaw_rate(0.0, 0.0, -G, 0.0, 0.0, 0.5) == pytest.approx(0.5)


def test_steps_carry_the_rotation_vector_heading_plus_the_offset() -> None:
    imu = _walking(cadence_hz=1.8, n_steps=20, amplitude=3.0, heading_deg=123.0)
    np.testing.assert_allclose(detect_steps(imu).heading, 123.0, atol=1e-9)
    shifted = detect_steps(imu, replace(PdrParams(), heading_offset_deg=-130.0))
    np.testing.assert_allclose(shifted.heading, 353.0, atol=1e-9)


def test_without_rotation_vector_gyro_bias_leaves_the_closed_form_offset() -> None:
    # Fixed point of ψ = (1 - α)(ψ + r Δt) + α u: ψ - u = (1 - α) r Δt / α, r = -bias.
    params = PdrParams()
    bias = -0.02
    imu = _walking(
        cadence_hz=1.8,
        n_steps=60,
        amplitude=3.0,
        heading_deg=60.0,
        rot=False,
        gyro_bias=bias,
        noise=0.0,
    )
    steps = detect_steps(imu, params)
    dt = params.grid_ms / 1000.0
    alpha = 1.0 - np.exp(-dt / params.mag_time_constant_s)
    expected = 60.0 + np.degrees((1 - alpha) * -bias * dt / alpha)
    settled = steps.t > imu.t[0] + 3000 + 10 * 1000 * params.mag_time_constant_s
    assert settled.sum() >= 10
    np.testing.assert_allclose(steps.heading[settled], expected, atol=1e-3)


def test_when_the_rotation_vector_stops_the_compass_takes_over_afresh() -> None:
    # 40 steps with a rotation vector, then the phone stops sending it: the gyro +
    # magnetometer heading, skipped while the rotation vector gave every heading, starts
    # from the magnetometer and gives the same heading
    imu = _walking(cadence_hz=1.8, n_steps=40, amplitude=3.0, heading_deg=75.0, noise=0.0)
    half = imu.t[0] + 3000 + 11_000
    rot = np.where((imu.t < half)[:, None], imu.rot, np.nan)
    mixed = ImuSamples(t=imu.t, acc=imu.acc, gyro=imu.gyro, mag=imu.mag, rot=rot)
    pdr = Pdr()
    steps = Steps.concat([pdr.update(b) for b in _chunks(mixed, np.full(200, 50))])
    assert (steps.t < half).sum() >= 15 and (steps.t > half).sum() >= 15
    np.testing.assert_allclose(steps.heading, 75.0, atol=1e-6)


def test_chunked_stream_equals_whole_stream_on_a_synthetic_walk() -> None:
    imu = _walking(cadence_hz=1.9, n_steps=30, amplitude=3.0, heading_deg=10.0, rot=False)
    whole = detect_steps(imu)
    rng = np.random.default_rng(3)
    pdr = Pdr()
    parts = [pdr.update(c) for c in _chunks(imu, rng.integers(1, 80, size=len(imu)))]
    _assert_same_steps(Steps.concat(parts), whole, heading_atol=1e-9)


@pytest.mark.skipif(not WALK.is_dir(), reason="ILC site1 recordings not present")
@pytest.mark.parametrize("rot", [True, False])
def test_chunked_with_snapshots_equals_whole_on_a_real_walk(rot: bool) -> None:
    imu = imu_samples(read_walk(sorted(WALK.glob("*.txt.gz"))[0]))
    if not rot:
        imu.rot = np.full_like(imu.rot, np.nan)
    whole = detect_steps(imu)
    assert len(whole) > 10
    rng = np.random.default_rng(7)
    pdr = Pdr()
    parts = []
    for chunk in _chunks(imu, rng.integers(1, 120, size=len(imu))):
        parts.append(pdr.update(chunk))
        # Round-trip the state through JSON, as a worker's snapshot store would.
        state = json.loads(
            json.dumps(
                {
                    k: v.tolist() if isinstance(v, np.ndarray) else v
                    for k, v in pdr.snapshot().items()
                }
            )
        )
        pdr = Pdr.from_snapshot(state)
    _assert_same_steps(Steps.concat(parts), whole, heading_atol=1e-9)


def test_a_long_pause_restarts_the_filters_in_any_chunking() -> None:
    a = _walking(cadence_hz=1.8, n_steps=10, amplitude=3.0, seed=1)
    b = _walking(cadence_hz=1.8, n_steps=14, amplitude=3.0, seed=2)
    shift = int(a.t[-1] - b.t[0]) + 5000
    joined = ImuSamples(
        t=np.r_[a.t, b.t + shift],
        acc=np.vstack([a.acc, b.acc]),
        gyro=np.vstack([a.gyro, b.gyro]),
        mag=np.vstack([a.mag, b.mag]),
        rot=np.vstack([a.rot, b.rot]),
    )
    whole = detect_steps(joined)
    assert len(whole) == 24
    pdr = Pdr()
    parts = [pdr.update(c) for c in _chunks(joined, np.full(len(joined), 33))]
    _assert_same_steps(Steps.concat(parts), whole)


def test_late_and_unsorted_samples() -> None:
    imu = _walking(cadence_hz=1.8, n_steps=20, amplitude=3.0)
    whole = detect_steps(imu)
    half = len(imu) // 2
    perm = np.random.default_rng(5).permutation(half)
    pdr = Pdr()
    first = pdr.update(
        ImuSamples(
            t=imu.t[:half][perm],
            acc=imu.acc[:half][perm],
            gyro=imu.gyro[:half][perm],
            mag=imu.mag[:half][perm],
            rot=imu.rot[:half][perm],
        )
    )
    # Resend the last 10 samples of the first half with the second half: they are late.
    second = pdr.update(_chunks(imu, np.array([half - 10, len(imu)]))[1])
    assert pdr.late == 10
    _assert_same_steps(Steps.concat([first, second]), whole)
