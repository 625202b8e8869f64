"""The per-scan k-NN cross-validated on whole held-out walks: reading age, neighbours."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.radiomap import Survey
from app.engine.scan_knn import LEVEL_POWERS, ReferenceScans, ScanKnnParams
from app.engine.scan_knn_cv import (
    FLOOR_CANDIDATES_DBM,
    K_CANDIDATES,
    PENALTY_CANDIDATES,
    POWER_CANDIDATES,
    WRONG_FLOOR_M,
    choose_neighbours,
    fix_spread,
    paired_scores,
    walk_errors,
)
from app.engine.tuning import one_standard_error_choice
from tests.engine.test_scan_knn import _walk


def _elsewhere(walk: int) -> Survey:
    """A walk on another floor hearing only transmitters nobody else hears."""
    n = 5
    return Survey(
        scan_t=np.arange(n, dtype=np.int64) * 1000,
        scan_xy=np.zeros((n, 2)),
        scan_floor=np.ones(n, dtype=np.int32),
        scan_walk=np.full(n, walk, dtype=np.int32),
        reading_scan=np.repeat(np.arange(n, dtype=np.int32), 2),
        reading_tx=np.tile(np.array([20, 21], dtype=np.int32), n),
        reading_rssi=np.full(2 * n, -60.0),
    )


def test_walks_are_scored_on_the_other_walks_scans_only() -> None:
    rng = np.random.default_rng(5)
    xs = np.arange(0.0, 40.5, 1.0)
    survey = Survey.concat([_walk(xs, rng, 0), _walk(xs + 0.5, rng, 1), _elsewhere(2)])
    (errors,) = walk_errors(survey, n_tx=22, folds=3, every=1)
    # the two corridor walks locate each other's scans within a few metres
    assert set(errors) == {0, 1}
    assert all(e < 3.0 for e in errors.values())
    # the walk elsewhere shares nothing with the rest once its own scans are held out:
    # scored against itself it would have been exact
    assert 2 not in errors
    assert walk_errors(survey, n_tx=22, folds=1) == [{}]


def test_a_scan_on_a_wrong_floor_counts_as_the_wrong_floor_error() -> None:
    rng = np.random.default_rng(6)
    xs = np.arange(0.0, 40.5, 1.0)
    lower, upper = _walk(xs, rng, 0), _walk(xs, rng, 1)
    upper = Survey(**(vars(upper) | {"scan_floor": np.ones(upper.n_scans, dtype=np.int32)}))
    (errors,) = walk_errors(Survey.concat([lower, upper]), n_tx=5, folds=2, every=4)
    assert errors == {0: WRONG_FLOOR_M, 1: WRONG_FLOOR_M}


def test_ages_are_compared_on_the_walks_all_scored_and_the_default_kept_unless_beaten() -> None:
    by_age = {
        2000: {0: 9.0, 1: 7.0, 2: 8.0},
        5000: {0: 6.0, 1: 5.0, 2: 5.5, 3: 1.0},
        8000: {0: 6.1, 1: 4.9, 2: 5.4},
    }
    scores = paired_scores(by_age)
    assert scores == {2000.0: [9.0, 7.0, 8.0], 5000.0: [6.0, 5.0, 5.5], 8000.0: [6.1, 4.9, 5.4]}
    # 8 s is better on average by less than its walk-by-walk spread: 5 s, the default, stays
    assert one_standard_error_choice(scores, 5000.0) == 5000.0
    assert one_standard_error_choice(scores, 2000.0) == 5000.0


def test_variants_locate_as_a_k_nn_built_with_their_constants() -> None:
    rng = np.random.default_rng(7)
    xs = np.arange(0.0, 40.5, 1.0)
    survey = Survey.concat([_walk(xs + 0.25 * w, rng, w) for w in range(4)])
    variants = [(3, 4.0), (30, 0.0)]
    found = walk_errors(survey, n_tx=5, folds=2, every=3, variants=variants)
    for (k, power), errors in zip(variants, found, strict=True):
        params = ScanKnnParams(k=k, weight_power=power)
        held = survey.scan_walk % 2 == 0
        refs = ReferenceScans(survey.select(~held), 5, params)
        rows = [np.flatnonzero(survey.reading_scan == j) for j in np.flatnonzero(held)[::3]]
        walk0 = [
            float(np.hypot(*(fix.xy - survey.scan_xy[j])))
            for j, r in zip(np.flatnonzero(held)[::3], rows, strict=True)
            if survey.scan_walk[j] == 0
            and (fix := refs.locate(survey.reading_tx[r], survey.reading_rssi[r])) is not None
        ]
        assert errors[0] == pytest.approx(np.mean(walk0), abs=1e-12)
    # an unweighted mean of 30 scans of a 41-scan corridor smears the ends: worse than 3
    assert np.mean(list(found[1].values())) > np.mean(list(found[0].values()))


def test_the_neighbours_chosen_are_the_rule_s_choice_among_paired_walk_scores() -> None:
    rng = np.random.default_rng(8)
    xs = np.arange(0.0, 40.5, 1.0)
    survey = Survey.concat([_walk(xs + 0.25 * w, rng, w) for w in range(4)])
    chosen, scores = choose_neighbours(survey, n_tx=5, folds=2)
    assert set(scores["floor_dbm"]) == set(FLOOR_CANDIDATES_DBM)
    assert set(scores["unshared_penalty"]) == set(PENALTY_CANDIDATES)
    assert set(scores["level_power"]) == {float(g) for g in LEVEL_POWERS}
    assert set(scores["weight_power"]) == set(POWER_CANDIDATES)
    assert set(scores["k"]) == {float(k) for k in K_CANDIDATES}
    assert chosen.floor_dbm == one_standard_error_choice(scores["floor_dbm"], -100.0)
    assert chosen.unshared_penalty == one_standard_error_choice(scores["unshared_penalty"], 50.0)
    assert chosen.level_power == one_standard_error_choice(scores["level_power"], 0.0)
    assert chosen.weight_power == one_standard_error_choice(scores["weight_power"], 4.0)
    assert chosen.k == one_standard_error_choice(scores["k"], 10.0)
    # every candidate was scored on the same walks
    assert len({len(v) for s in scores.values() for v in s.values()}) == 1
    # a survey of one walk cannot be cross-validated: the defaults stay
    one = survey.select(survey.scan_walk == 0)
    assert choose_neighbours(one, n_tx=5, folds=2) == (ScanKnnParams(), {})


def test_the_fix_spread_is_the_rms_of_the_held_out_errors_on_the_right_floor() -> None:
    rng = np.random.default_rng(9)
    xs = np.arange(0.0, 40.5, 1.0)
    lower = Survey.concat([_walk(xs + 0.25 * w, rng, w) for w in range(4)])
    # a fifth walk on another floor hearing the same transmitters: its scans land on floor 0
    upper = _walk(xs, rng, 4)
    upper = Survey(**(vars(upper) | {"scan_floor": np.ones(upper.n_scans, dtype=np.int32)}))
    survey = Survey.concat([lower, upper])
    params = ScanKnnParams(k=3)
    spread = fix_spread(survey, 5, folds=5, params=params, every=1)
    squares = []
    for fold in range(5):
        held = survey.scan_walk % 5 == fold
        refs = ReferenceScans(survey.select(~held), 5, params)
        for j in np.flatnonzero(held):
            r = np.flatnonzero(survey.reading_scan == j)
            fix = refs.locate(survey.reading_tx[r], survey.reading_rssi[r])
            if fix is not None and fix.floor == survey.scan_floor[j]:
                squares.append(float(np.sum((fix.xy - survey.scan_xy[j]) ** 2)))
    assert spread == pytest.approx(np.sqrt(np.mean(squares)), rel=1e-12)
    assert 0.0 < spread < 3.0
    assert fix_spread(survey.select(survey.scan_walk == 0), 5, folds=5, params=params) is None
