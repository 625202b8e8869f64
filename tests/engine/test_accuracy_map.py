"""A-priori accuracy: Grinyak's hall against Monte-Carlo least squares, closed forms, the grid."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.accuracy_map import AccuracyParams, accuracy_at, accuracy_grid, floor_accuracy
from app.engine.lateration.accuracy import path_loss_B
from app.engine.lateration.solver import LaterationParams, solve
from app.engine.plan import FloorPlan
from app.engine.site import Emitters, Floor, SiteModel

# Grinyak 2020, Table 1: a 10 × 10 × 4 m hall; σ_u² = 25 dB², 50 readings per beacon.
SIGMA_DB = 5.0
SAMPLES = 50
# The paper does not print n; free space (n = 2) reproduces its numbers (see AccuracyParams).
B_HALL = path_loss_B(2.0)
A_HALL = -59.0
_CORNERS = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
_WALL_MIDS = np.array([[5.0, 0.0], [10.0, 5.0], [5.0, 10.0], [0.0, 5.0]])
FLOOR_4 = np.column_stack([_CORNERS, np.zeros(4)])
"""Variant 1: 4 beacons on the floor in the corners."""
CORNERS_8 = np.vstack([FLOOR_4, np.column_stack([_CORNERS, np.full(4, 4.0)])])
"""Variant 2: 4 on the floor and 4 on the ceiling in the corners."""
_RING = np.vstack([_CORNERS, _WALL_MIDS])
HALL_17 = np.vstack(
    [
        np.column_stack([_RING, np.zeros(8)]),
        np.column_stack([_RING, np.full(8, 4.0)]),
        [[5.0, 5.0, 4.0]],
    ]
)
"""Variant 3: floor and ceiling corners and wall midpoints, and one in the ceiling's centre."""


def _predicted(layout: np.ndarray, point: np.ndarray) -> np.ndarray:
    sigma, _, dims = accuracy_at(
        point[None],
        layout,
        np.full(len(layout), SIGMA_DB),
        model="rssi",
        B=np.full(len(layout), B_HALL),
        samples=SAMPLES,
    )
    assert dims[0] == 3
    return sigma[0]


@pytest.mark.parametrize(
    ("layout", "point"),
    [
        (FLOOR_4, (5.0, 5.0, 3.0)),
        (CORNERS_8, (5.0, 5.0, 3.0)),
        (CORNERS_8, (3.0, 6.0, 2.0)),
        (HALL_17, (5.0, 5.0, 2.0)),
        (HALL_17, (1.0, 3.0, 2.0)),
    ],
)
def test_predicted_sigma_matches_monte_carlo_least_squares(layout, point) -> None:
    """D = (Hᵀ Q⁻¹ H)⁻¹ agrees within 10 % with the spread of 2,000 simulated fixes."""
    rng = np.random.default_rng(2020)
    p = np.array(point)
    k = len(layout)
    mean = A_HALL - B_HALL * np.log(np.linalg.norm(layout - p, axis=1))
    readings = mean[None, :, None] + rng.normal(0.0, SIGMA_DB, (2000, k, SAMPLES))
    fixes = solve(
        "rssi",
        layout,
        readings.mean(axis=2),
        np.full(k, SIGMA_DB / np.sqrt(SAMPLES)),
        A=np.full(k, A_HALL),
        B=np.full(k, B_HALL),
        dims=3,
        x0=np.tile(p, (2000, 1)),
        params=LaterationParams(loss="linear", max_iter=50),
    )
    assert fixes.ok.mean() > 0.97
    spread = fixes.position[fixes.ok].std(axis=0)
    np.testing.assert_allclose(spread, _predicted(layout, p), rtol=0.10)


def test_the_papers_findings() -> None:
    """4 floor beacons: ≈0.5 m flat, ≈1 m height at the centre, height twice worse low down;
    17 beacons: under 0.2 m on every axis at the centre."""
    centre_high = _predicted(FLOOR_4, np.array([5.0, 5.0, 3.0]))
    centre_low = _predicted(FLOOR_4, np.array([5.0, 5.0, 1.0]))
    assert 0.4 < centre_high[0] < 0.6 and centre_high[0] == pytest.approx(centre_high[1])
    assert 0.7 < centre_high[2] < 1.2 and centre_high[2] > 1.5 * centre_high[0]
    assert centre_low[2] > 2.0 * centre_high[2]
    eight = _predicted(CORNERS_8, np.array([1.0, 9.0, 2.0]))
    assert eight[2] < 0.3
    seventeen = _predicted(HALL_17, np.array([5.0, 5.0, 3.0]))
    assert (seventeen < 0.2).all()


def test_uwb_square_closed_form_and_height_fallback() -> None:
    """Anchors in the object's plane: 3-D unobservable, 2-D σ = σ_r / √(2M) at the centre."""
    anchors = np.array([[0.0, 0, 1.0], [8, 0, 1.0], [8, 8, 1.0], [0, 8, 1.0]])
    sigma, cond, dims = accuracy_at(
        np.array([[4.0, 4.0, 1.0], [4.0, 4.0, 2.5]]),
        anchors,
        np.full(4, 0.1),
        model="range",
        samples=4,
    )
    assert dims.tolist() == [2, 3]
    np.testing.assert_allclose(sigma[0, :2], 0.1 / np.sqrt(2 * 4), rtol=1e-9)
    assert np.isnan(sigma[0, 2]) and cond[0] == pytest.approx(1.0)
    assert np.isfinite(sigma[1]).all()


def test_out_of_range_and_missing_emitters_make_cells_unobservable() -> None:
    anchors = np.array([[0.0, 0, 2.0], [8, 0, 2.5], [8, 8, 2.0], [0, 8, 2.5]])
    far = np.array([[30.0, 30.0, 1.0]])
    sigma, cond, dims = accuracy_at(far, anchors, np.full(4, 0.1), model="range", max_range=10.0)
    assert dims[0] == 0 and np.isnan(sigma).all() and np.isnan(cond).all()
    sigma, _, dims = accuracy_at(far, np.zeros((0, 3)), np.zeros(0), model="range")
    assert dims[0] == 0 and np.isnan(sigma).all()


def test_grid_is_the_pointwise_map_whatever_the_chunking() -> None:
    B = np.full(len(CORNERS_8), B_HALL)
    std = np.full(len(CORNERS_8), SIGMA_DB)
    grid = accuracy_grid((0.0, 0.0, 10.0, 10.0), 1.0, 2.0, CORNERS_8, std, model="rssi", B=B)
    small = accuracy_grid(
        (0.0, 0.0, 10.0, 10.0),
        1.0,
        2.0,
        CORNERS_8,
        std,
        model="rssi",
        B=B,
        params=AccuracyParams(chunk_cells=7),
    )
    assert grid.shape == (10, 10)
    np.testing.assert_array_equal(grid.sigma_x, small.sigma_x)
    centres = grid.centres()
    for row, col in [(0, 0), (3, 7), (9, 9)]:
        x, y = centres[row, col]
        sigma, cond, _ = accuracy_at(np.array([[x, y, 2.0]]), CORNERS_8, std, model="rssi", B=B)
        np.testing.assert_allclose(
            [grid.sigma_x[row, col], grid.sigma_y[row, col], grid.sigma_z[row, col]], sigma[0]
        )
        assert grid.cond[row, col] == pytest.approx(cond[0])
    # symmetry of the layout: σx at (x, y) is σy at (y, x)
    np.testing.assert_allclose(grid.sigma_x, grid.sigma_y.T, rtol=1e-9)


def test_floor_map_uses_defaults_and_renders_nulls() -> None:
    plan = FloorPlan.from_raster(origin=np.zeros(2), cell=1.0, free=np.ones((4, 6), bool))
    tx = Emitters(
        ids=("a", "b", "c", "d"),
        floor=np.zeros(4, np.int32),
        xyz=np.array([[0.0, 0, 2], [6, 0, 2], [6, 4, 2], [0, 4, 2]]),
        A=np.full(4, -60.0),
        B=np.array([np.nan, 9.0, 9.0, 9.0]),
        sigma=np.array([np.nan, 4.0, 4.0, 4.0]),
    )
    site = SiteModel("s", (Floor("F", 0, 4.0, plan),), transmitters=tx, anchors=tx)
    ble = floor_accuracy(site, 0, "ble", z=2.0, cell=2.0, samples=10)
    explicit = accuracy_grid(
        plan.bounds,
        2.0,
        2.0,
        tx.xyz,
        np.array([5.0, 4.0, 4.0, 4.0]),
        model="rssi",
        B=np.array([path_loss_B(2.0), 9.0, 9.0, 9.0]),
        samples=10,
    )
    np.testing.assert_array_equal(ble.sigma_x, explicit.sigma_x)
    doc = ble.to_json()
    assert doc["shape"] == [2, 3] and doc["cell"] == 2.0
    assert all(v is None for row in doc["sigma_z"] for v in row)  # emitters' plane: 2-D only
    uwb = floor_accuracy(site, 0, "uwb", z=1.0, cell=2.0, samples=1)
    assert np.isfinite(uwb.sigma_z).all()
