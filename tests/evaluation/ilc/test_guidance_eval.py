"""The guidance evaluation reads a grid at positions as the grid's cells say: walkable cells
give their value (NaN unsurveyed), positions off the walkable cells or the grid give none."""

from __future__ import annotations

import numpy as np

from app.engine.survey_guidance import GuidanceGrid, GuidanceParams
from app.evaluation.ilc.guidance import expected_at


def test_expected_at_reads_the_cell_under_each_position() -> None:
    walkable = np.array([[True, True, False], [True, True, True]])
    error = np.array([[1.0, np.nan, np.nan], [3.0, 4.0, 5.0]])
    grid = GuidanceGrid(
        origin=np.array([10.0, 20.0]),
        walkable=walkable,
        error_m=error,
        distance_m=np.where(walkable, 1.0, np.nan),
        scans=4,
        params=GuidanceParams(cell_m=2.0),
    )
    xy = np.array(
        [[10.5, 20.5], [12.5, 21.9], [14.5, 20.5], [15.9, 23.9], [9.9, 20.5], [11.0, 24.1]]
    )
    floor = np.array([0, 0, 0, 0, 0, 1])
    value, on_grid = expected_at({0: grid, 1: grid}, floor, xy)
    # (0, 0) = 1; (0, 1) unsurveyed; (0, 2) not walkable; (1, 2) = 5; left of x0; above the top
    assert on_grid.tolist() == [True, True, False, True, False, False]
    np.testing.assert_array_equal(value, [1.0, np.nan, np.nan, 5.0, np.nan, np.nan])
