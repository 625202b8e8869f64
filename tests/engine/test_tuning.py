"""A site's constants chosen from its surveys, stored and read back."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.engine.hmm.params import HmmParams
from app.engine.hmm.validate import (
    HeldWalk,
    WalkResult,
    calibrate_radius,
    score_walk,
    smoother_scores,
)
from app.engine.pdr_fit import WalkPdr
from app.engine.samples import Estimate, ImuSamples, RssiReadings
from app.engine.tuning import (
    HEADING_STD_RANGE_DEG,
    SiteTuning,
    heading_spread,
    one_move_choice,
    one_standard_error_choice,
    tune_site,
)


def _walk(errors: list[float], distance: float = 40.0, stride_sum: float = 100.0) -> WalkPdr:
    return WalkPdr(
        walk_id="w",
        floor="F1",
        distance=distance,
        stride_sum=stride_sum,
        n_steps=60,
        duration_s=40.0,
        segment_error=np.array(errors, dtype=float),
    )


def test_a_rotated_building_is_learned_from_its_surveys() -> None:
    # every survey segment's steps point 30° clockwise of the walked direction
    walks = [_walk([29.0, 31.0, 30.5, 29.5]), _walk([30.0, 28.0, 32.0])]
    tuning = tune_site(walks, None)
    assert tuning.heading_offset_deg == pytest.approx(-30.0, abs=0.5)
    # K fits the walked distance: 80 m over 200 swing units
    assert tuning.weinberg_k == pytest.approx(0.4)
    assert tuning.pdr_walks == 2
    # the spread once the rotation is removed is small, bounded below
    assert tuning.heading_std_deg == HEADING_STD_RANGE_DEG[0]
    assert tuning.pdr().heading_offset_deg == tuning.heading_offset_deg


def test_heading_spread_is_robust_to_one_wild_segment() -> None:
    errors = [10.0, -10.0, 12.0, -12.0, 8.0, -8.0, 170.0]
    spread = heading_spread([_walk(errors)], 0.0)
    # σ ≈ 1.4826 × 16 (the MAD), where a standard deviation would be over 60°
    assert spread is not None and 20.0 < spread < 30.0
    assert heading_spread([_walk([1.0])], 0.0) is None


def test_without_surveys_the_defaults_stand() -> None:
    assert tune_site([], None) == SiteTuning.defaults()
    hmm = SiteTuning.defaults().hmm()
    assert hmm == HmmParams()


def test_stored_tuning_reads_back_and_missing_values_take_defaults() -> None:
    tuning = SiteTuning.defaults()
    tuned = SiteTuning.from_dict(tuning.as_dict() | {"wknn_k": 12, "emission_weight": 0.05})
    assert tuned.wknn_k == 12 and tuned.wknn().k == 12
    # the HMM restarts from its own k: a large WKNN k averages far points on a sparse map
    assert tuned.hmm().k == HmmParams().k
    assert tuned.hmm().emission_weight == 0.05
    # a build stored before some constant was chosen keeps that constant's default
    assert SiteTuning.from_dict({"wknn_k": 3, "unknown": 1}).floor_weight == tuning.floor_weight


def test_the_radius_calibration_makes_the_radius_hold_68_percent_of_the_errors() -> None:
    rng = np.random.default_rng(2)
    error = np.abs(rng.normal(0.0, 5.0, 2000))

    def held(radius: np.ndarray, scale: float, floor: float) -> float:
        return float(np.mean(error <= np.maximum(1.0, np.hypot(scale * radius, floor))))

    # a radius too narrow gets a floor in quadrature
    narrow = np.full(2000, 1.0)
    scale, floor = calibrate_radius(error, narrow, 1.0)
    assert scale == 1.0 and floor > 0.0
    assert held(narrow, scale, floor) == pytest.approx(0.68, abs=0.005)
    # a radius too wide (it holds every error) shrinks, with no floor
    wide = 3.0 * error + rng.uniform(0.0, 2.0, 2000)
    scale, floor = calibrate_radius(error, wide, 1.0)
    assert scale < 1.0 and floor == 0.0
    assert held(wide, scale, floor) == pytest.approx(0.68, abs=0.005)
    assert calibrate_radius(np.zeros(0), np.zeros(0), 1.0) == (1.0, 0.0)


def test_a_candidate_replaces_the_default_only_when_better_by_more_than_luck() -> None:
    rng = np.random.default_rng(4)
    # walks differ far more from each other than candidates do on the same walk
    hardness = 10.0 + rng.normal(0.0, 5.0, 30)
    noisy = {w: (hardness + rng.normal(0.0, 1.0, 30)).tolist() for w in (0.05, 0.1, 0.2, 0.35)}
    # a hair better on average, but not walk by walk: the default stays
    noisy[0.1] = (np.asarray(noisy[0.2]) - 0.1 + rng.normal(0.0, 1.0, 30)).tolist()
    assert one_standard_error_choice(noisy, 0.2) == 0.2
    # better on the same walks by more than the walk-by-walk luck: chosen, even though
    # the walks' own spread (5 m) dwarfs the gain
    noisy[0.05] = (np.asarray(noisy[0.2]) - 1.0 + rng.normal(0.0, 0.3, 30)).tolist()
    assert one_standard_error_choice(noisy, 0.2) == 0.05


def test_off_is_chosen_only_when_it_beats_every_nearer_candidate() -> None:
    rng = np.random.default_rng(5)
    hardness = 10.0 + rng.normal(0.0, 5.0, 40)
    scores = {f: (hardness + rng.normal(0.0, 0.2, 40)).tolist() for f in (0.0, 10.0, 20.0)}
    # all alike: the default
    assert one_standard_error_choice(scores, 10.0) == 10.0
    # the fix hurts on every walk: off
    scores[10.0] = (np.asarray(scores[0.0]) + 0.8).tolist()
    scores[20.0] = (np.asarray(scores[0.0]) + 1.5).tolist()
    assert one_standard_error_choice(scores, 10.0) == 0.0


def test_at_most_one_replayed_constant_moves_and_it_is_the_move_that_erred_least() -> None:
    rng = np.random.default_rng(6)
    hardness = 10.0 + rng.normal(0.0, 5.0, 40)

    def alike(values: tuple[float, ...]) -> dict[float, list[float]]:
        return {v: (hardness + rng.normal(0.0, 0.05, 40)).tolist() for v in values}

    weights, noises = alike((0.1, 0.2)), alike((0.05, 0.5))
    # nothing better by more than luck: every default stands
    assert one_move_choice([weights, noises], (0.2, 0.05)) == (0.2, 0.05)
    # both would move, the noise by more: only the noise moves (that pair was replayed,
    # the pair of both moves was not)
    weights[0.1] = (hardness - 0.5).tolist()
    noises[0.5] = (hardness - 1.0).tolist()
    assert one_move_choice([weights, noises], (0.2, 0.05)) == (0.2, 0.5)
    # a constant nobody replayed keeps its default
    assert one_move_choice([weights, {}], (0.2, 0.05)) == (0.1, 0.05)


def test_the_transition_noise_reaches_the_hmm_and_old_builds_keep_the_default() -> None:
    tuning = replace(SiteTuning.defaults(), walk_noise_m2_per_s=0.5)
    assert tuning.hmm().walk_noise_m2_per_s == 0.5
    assert SiteTuning.from_dict(tuning.as_dict()) == tuning
    default = HmmParams().walk_noise_m2_per_s
    assert SiteTuning.from_dict({"fix_nats": 10.0}).hmm().walk_noise_m2_per_s == default


def _replayed_walk(seed: int) -> WalkResult:
    """A straight walk at 1 m/s whose live positions err by a persistent ~3 m."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, 60_000, 500)
    truth = np.stack([t / 1000.0, np.zeros(t.size)], axis=1)
    drift = np.cumsum(rng.normal(0.0, 0.5, truth.shape), axis=0)
    estimates = [
        Estimate(int(ti), float(p[0]), float(p[1]), 0.0, 0, 90.0, 3.0, 1.0, "hmm", (o[0], o[1]))
        for ti, p, o in zip(t, truth + drift, truth.tolist(), strict=True)
    ]
    waypoints = np.array([[0.0, 0.0, 0.0], [60_000.0, 60.0, 0.0]])
    walk = HeldWalk(RssiReadings(), ImuSamples(), waypoints, 0)
    result = score_walk(walk, estimates)
    assert result is not None
    return result


def test_the_smoothers_are_scored_on_the_radius_the_server_reports() -> None:
    replays = [_replayed_walk(seed) for seed in range(3)]
    # a calibrated radius twice the replayed one weighs the positions as a fix scale of 2
    doubled = smoother_scores(replays, (2.0, 0.0), 1.0, [1.0])
    plain = smoother_scores(replays, (1.0, 0.0), 1.0, [1.0, 2.0])
    for stage in ("fixed_lag", "full_pass"):
        assert len(doubled[stage][1.0]) == len(replays)
        assert doubled[stage][1.0] == pytest.approx(plain[stage][2.0])
        # and smoothing a drifting track against exact steps beats the live track
        assert np.mean(plain[stage][1.0]) < np.mean([r.score for r in replays])


def test_the_smoothers_take_the_sites_fix_scales() -> None:
    tuning = replace(SiteTuning.defaults(), lag_fix_scale=2.0, pass_fix_scale=4.0)
    assert tuning.fixed_lag().fix_scale == 2.0 and tuning.full_pass().fix_scale == 4.0
    assert SiteTuning.from_dict(tuning.as_dict()) == tuning
    # a build stored before the smoothers were tuned weighs positions by their radius
    assert SiteTuning.from_dict({"fix_nats": 10.0}).full_pass().fix_scale == 1.0
