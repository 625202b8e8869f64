"""The HMM's online heading-bias and step-scale fit (``app.engine.hmm.motion_fit``)."""

from __future__ import annotations

import math

import numpy as np

from app.engine.hmm.motion_fit import MotionFit
from app.workers import snapshots

FIX_SIGMA_M = 5.0
"""How far the synthetic fixes err (m, per axis)."""


def fit() -> MotionFit:
    """A fit with the HMM's default prior, time constant and gate."""
    return MotionFit(
        prior_m2=50.0, tau_s=120.0, min_scale=0.6, max_scale=1.6, fix_sigma_m=FIX_SIGMA_M, gate=9.0
    )


def walk(length_m: float, scans: int) -> np.ndarray:
    """Raw step-track positions (complex) at ``scans`` scans along an L: east, then north."""
    s = np.linspace(0.0, length_m, scans)
    half = length_m / 2
    return np.where(s < half, s + 0j, half + 1j * (s - half))


def feed(
    motion: MotionFit, odometry: np.ndarray, truth: complex, seed: int, scans: range | None = None
) -> None:
    """Add one scan every 3 s (those numbered ``scans``, default all): the raw track and a
    fix of where the walker truly was."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, FIX_SIGMA_M, (odometry.size, 2))
    for k in scans if scans is not None else range(odometry.size):
        fix = 20.0 + 7.0j + truth * odometry[k] + complex(*noise[k])
        motion.add(3000 * k, complex(odometry[k]), fix)


def test_a_phone_turned_a_quarter_turn_with_a_long_stride_is_learned_from_noisy_fixes() -> None:
    # the walker went 1.3 times as far as the steps say, 90° counter-clockwise of them
    motion = fit()
    feed(motion, walk(80.0, 30), 1.3 * np.exp(1j * math.pi / 2), seed=1)
    beta, scale = motion.rotation_scale()
    assert abs(math.degrees(beta) - 90.0) < 6.0
    # the gate keeps a scale correction short of what the noisy fixes say, never past it
    assert 1.1 < scale <= 1.3


def test_steps_that_need_no_correction_are_left_nearly_as_they_are() -> None:
    for seed in range(5):
        motion = fit()
        feed(motion, walk(80.0, 30), 1.0 + 0j, seed=seed)
        beta, scale = motion.rotation_scale()
        assert abs(math.degrees(beta)) < 3.0
        assert abs(scale - 1.0) < 0.03


def test_a_track_too_short_to_tell_is_barely_corrected() -> None:
    # three metres of steps cannot say which way a phone is turned, whatever the fixes say
    motion = fit()
    feed(motion, walk(3.0, 4), np.exp(1j * math.pi / 2), seed=3)
    beta, scale = motion.rotation_scale()
    assert abs(math.degrees(beta)) < 5.0
    assert abs(scale - 1.0) < 0.05


def test_old_scans_fade_so_a_phone_put_away_differently_is_followed() -> None:
    motion = fit()
    track = walk(80.0, 30)
    feed(motion, track, 1.0 + 0j, seed=4)
    # then ten minutes later, the same walk with the phone turned 90° clockwise
    rng = np.random.default_rng(5)
    for k, o in enumerate(track):
        fix = np.exp(-1j * math.pi / 2) * o + complex(*rng.normal(0.0, FIX_SIGMA_M, 2))
        motion.add(600_000 + 3000 * k, complex(o) + 500.0, fix)
    beta, _ = motion.rotation_scale()
    assert abs(math.degrees(beta) + 90.0) < 15.0


def test_a_fit_resumed_from_its_snapshot_continues_exactly() -> None:
    track, truth = walk(60.0, 20), 1.2 * np.exp(0.5j)
    straight, first = fit(), fit()
    feed(straight, track, truth, seed=6)
    feed(first, track, truth, seed=6, scans=range(10))
    # through the workers' serialisation: plain arrays and numbers only
    state = snapshots.decode(snapshots.encode({"m": first.snapshot()}))["m"]
    resumed = fit()
    resumed.restore(state)
    assert resumed.rotation_scale() == first.rotation_scale()
    feed(resumed, track, truth, seed=6, scans=range(10, track.size))
    assert resumed.rotation_scale() == straight.rotation_scale()
