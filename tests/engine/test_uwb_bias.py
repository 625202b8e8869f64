"""UWB range biases: the self-calibration equations by hand, and survey calibration."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.uwb_bias import (
    BiasParams,
    accumulate,
    residual_projector,
    solve_biases,
    survey_biases,
)
from tests.engine.tag_sim import ANCHORS


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
