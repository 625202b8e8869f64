"""Scoring of estimates against waypoints and the table statistics, on hand-made cases."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.samples import Estimate
from app.evaluation.ilc.score import WalkScore, path_direction, score_walk, summarise
from app.evaluation.ilc.table import format_cpu, table_cells

# A walk east along y = 0 from x = 0 (t = 0) to x = 10 (t = 10 s), standing there
# until t = 20 s, then north to (10, 10) at t = 30 s.
WAYPOINTS = np.array(
    [[0, 0.0, 0.0], [10_000, 10.0, 0.0], [20_000, 10.0, 0.0], [30_000, 10.0, 10.0]]
)


def _est(t: int, x: float, y: float, floor: int = 0, heading: float = float("nan")) -> Estimate:
    return Estimate(t, x, y, 0.0, floor, heading, 1.0, 1.0, "test")


def test_path_direction_is_clockwise_from_north_and_nan_when_standing() -> None:
    t = np.array([-1, 5_000, 15_000, 25_000, 30_001])
    d = path_direction(WAYPOINTS, t)
    assert np.isnan(d[0]) and np.isnan(d[-1])  # outside the span
    assert d[1] == pytest.approx(90.0)  # east
    assert np.isnan(d[2])  # standing: no direction
    assert d[3] == pytest.approx(0.0)  # north


def test_score_walk_interpolates_truth_and_splits_floor_from_distance() -> None:
    estimates = [
        _est(5_000, 5.0, 3.0, heading=100.0),  # truth (5, 0): 3 m, heading off by 10°
        _est(7_500, 7.5, -4.0, heading=80.0),  # truth (7.5, 0): 4 m, off by 10°
        _est(25_000, 10.0, 5.0, floor=2, heading=180.0),  # wrong floor, heading off 180°
        _est(40_000, 0.0, 0.0),  # after the last waypoint: not scored
        _est(15_000, 12.0, 0.0, heading=45.0),  # standing: error 2 m, no heading truth
    ]
    s = score_walk(WAYPOINTS, 0, estimates)
    assert s.floor_ok.tolist() == [True, True, False, True]
    np.testing.assert_allclose(s.error[[0, 1, 3]], [3.0, 4.0, 2.0])
    assert np.isnan(s.error[2])
    np.testing.assert_allclose(s.heading_error[:3], [10.0, 10.0, 180.0])
    assert np.isnan(s.heading_error[3])


def test_summary_statistics_on_a_hand_made_case() -> None:
    errors = np.array([1.0, 2.0, 3.0, 4.0, np.nan, 10.0, np.nan])
    ok = np.isfinite(errors)
    # reported radii: errors 1, 3 and 10 fall inside theirs, 2 and 4 outside
    a = WalkScore(
        ok[:4], errors[:4], np.array([10.0, np.nan, 30.0, 20.0]), np.array([1.0, 1.5, 5.0, 3.0])
    )
    b = WalkScore(
        ok[4:], errors[4:], np.array([np.nan, 350.0 - 340.0, 0.0]), np.array([9.0, 12.0, 1.0])
    )
    row = summarise("m", [a, b], cpu_s=0.5, updates=1000)
    assert row.n == 7 and row.walks == 2
    assert row.mean == pytest.approx(4.0)  # (1 + 2 + 3 + 4 + 10) / 5
    assert row.p50 == pytest.approx(3.0)
    assert row.p75 == pytest.approx(4.0)
    # numpy's linear rule: rank 0.95 × 4 = 3.8 → 4 + 0.8 × (10 - 4)
    assert row.p95 == pytest.approx(8.8)
    assert row.floor_error == pytest.approx(2 / 7)
    assert row.heading_error == pytest.approx(14.0) and row.n_heading == 5
    assert row.in_accuracy == pytest.approx(3 / 5)  # of the five on the right floor
    assert row.cpu_per_update_s == pytest.approx(5e-4)
    cells = table_cells(row)
    assert cells[3:8] == ["4.00", "3.00", "4.00", "8.80", "28.57%"]
    assert cells[-3] == "60%"
    # radii 1, 1.5, 5, 3, 12 against errors 1, 2, 3, 4, 10: one pair swapped in rank
    assert row.radius_rank == pytest.approx(0.9)
    assert cells[-2] == "0.90"
    assert cells[-1] == "500 µs"


def test_summary_of_no_estimates_is_nan_not_an_error() -> None:
    row = summarise("m", [], cpu_s=0.0, updates=0)
    assert row.n == 0 and np.isnan(row.mean) and np.isnan(row.floor_error)
    assert table_cells(row)[3] == "—" and table_cells(row)[-1] == "—"


def test_format_cpu_switches_to_milliseconds() -> None:
    assert format_cpu(87e-6) == "87 µs"
    assert format_cpu(3.5e-3) == "3.50 ms"
