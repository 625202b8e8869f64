"""The per-scan floor classifier: access points' home floors from the survey, and a floor told
right where that floor was never surveyed but the floor below it was."""

from __future__ import annotations

import numpy as np
from scipy import sparse

from app.engine.hmm.floor_classifier import (
    FloorClassifierParams,
    fit_floor_classifier,
    home_floors,
)

SLAB_DB = 25.0
"""Loss through one floor in the synthetic building."""

AP_X = np.linspace(0.0, 100.0, 11)
"""Each floor has an access point every 10 m along a 100 m corridor."""


def _levels(x: float, floor: int) -> np.ndarray:
    """Levels (dB above the floor) a phone at ``x`` on ``floor`` hears from the 22 access
    points: 60 dB beside one, 0.4 dB less a metre, ``SLAB_DB`` less a floor away."""
    ap_floor = np.repeat([0, 1], AP_X.size)
    ap_x = np.tile(AP_X, 2)
    return np.maximum(60.0 - 0.4 * np.abs(x - ap_x) - SLAB_DB * np.abs(floor - ap_floor), 0.0)


def _survey() -> tuple[sparse.csr_matrix, np.ndarray]:
    """Floor 0 surveyed along its whole corridor, floor 1 in its west half only."""
    places = [(x, 0) for x in np.arange(0.0, 100.5, 2.0)] + [
        (x, 1) for x in np.arange(0.0, 50.5, 2.0)
    ]
    rows = np.array([_levels(x, f) for x, f in places])
    return sparse.csr_matrix(rows), np.array([f for _, f in places])


def test_an_access_point_is_homed_on_the_floor_that_hears_it_loudest() -> None:
    references, labels = _survey()
    home = home_floors(references, labels, 2, FloorClassifierParams())
    assert home.tolist() == [0] * AP_X.size + [1] * AP_X.size


def test_the_floor_is_told_where_only_the_floor_below_was_surveyed() -> None:
    references, labels = _survey()
    column = np.arange(2 * AP_X.size)
    model = fit_floor_classifier(references, labels, 2, column, FloorClassifierParams())
    for x in np.arange(60.0, 100.5, 5.0):
        upstairs = model.log_probs(column, _levels(x, 1))
        downstairs = model.log_probs(column, _levels(x, 0))
        assert np.exp(upstairs[1]) > 0.9 and np.exp(downstairs[0]) > 0.9
    again = fit_floor_classifier(references, labels, 2, column, FloorClassifierParams())
    assert np.array_equal(again.weights, model.weights) and np.array_equal(again.bias, model.bias)


def test_a_scan_of_unknown_transmitters_says_nothing_of_the_floor() -> None:
    references, labels = _survey()
    column = np.concatenate([np.arange(2 * AP_X.size), [-1]])
    model = fit_floor_classifier(references, labels, 2, column, FloorClassifierParams())
    # transmitter 22 is no reference column; 99 is beyond the site's table
    uniform = model.log_probs(np.array([22, 99]), np.array([40.0, 30.0]))
    assert np.allclose(uniform, np.log(0.5))
