"""Choosing how old a WiFi reading may be: per-scan k-NN errors of whole held-out walks."""

from __future__ import annotations

import numpy as np

from app.engine.radiomap import Survey
from app.engine.tuning import one_standard_error_choice
from app.engine.wifi_age import WRONG_FLOOR_M, paired_scores, walk_errors
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
    errors = walk_errors(survey, n_tx=22, folds=3, every=1)
    # the two corridor walks locate each other's scans within a few metres
    assert set(errors) == {0, 1}
    assert all(e < 3.0 for e in errors.values())
    # the walk elsewhere shares nothing with the rest once its own scans are held out:
    # scored against itself it would have been exact
    assert 2 not in errors
    assert walk_errors(survey, n_tx=22, folds=1) == {}


def test_a_scan_on_a_wrong_floor_counts_as_the_wrong_floor_error() -> None:
    rng = np.random.default_rng(6)
    xs = np.arange(0.0, 40.5, 1.0)
    lower, upper = _walk(xs, rng, 0), _walk(xs, rng, 1)
    upper = Survey(**(vars(upper) | {"scan_floor": np.ones(upper.n_scans, dtype=np.int32)}))
    errors = walk_errors(Survey.concat([lower, upper]), n_tx=5, folds=2, every=4)
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
