"""Track-to-plan fitting by dynamic programming (Voronov et al.).

References: a second, loop-by-loop implementation of the paper's forward and
backward passes using only ``FloorPlan.is_free`` sampled along each link;
``FloorPlan.segment_free`` for the raster wall test; exact shapely
intersections with the wall segments; hand-worked cases.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import shapely

from app.engine.plan import FloorPlan, burn_segments
from app.engine.trackfit.fit import (
    RELAX_CROSSED,
    RELAX_DEAD_RECKONED,
    RELAX_NONE,
    RELAX_WIDENED,
    TrackFitParams,
    fit_track,
)
from app.engine.trackfit.grid import NONE, cell_grid, segments_free
from app.engine.trackfit.step import advance, best_per_cell

# Fig. 2 of the paper as a plan: a corridor (y < 2) under two rooms split by a
# wall at x = 6, entered through doors at 3 < x < 4 and 8 < x < 9.
W, H = 12.0, 8.0
WALLS = np.array(
    [
        [0, 0, W, 0],
        [W, 0, W, H],
        [W, H, 0, H],
        [0, H, 0, 0],
        [0, 2, 3, 2],
        [4, 2, 8, 2],
        [9, 2, 12, 2],
        [6, 2, 6, 8],
    ],
    dtype=float,
)
WALL_LINES = shapely.MultiLineString([w.reshape(2, 2) for w in WALLS])
# Along the corridor from (1, 1), then north through the right-hand door.
ROUTE = np.array(
    [[1, 1], [2.5, 1], [4, 1], [5.5, 1], [7, 1], [8.5, 1], [8.5, 2.5], [8.5, 4], [8.5, 5.5]],
    dtype=float,
)


def fig2_plan(cell: float = 0.1) -> FloorPlan:
    """Rasterise the Fig. 2 layout; the origin keeps walls and cell edges apart."""
    origin = np.array([-0.45, -0.45])
    nx, ny = round((W + 1) / cell), round((H + 1) / cell)
    xs = origin[0] + (np.arange(nx) + 0.5) * cell
    ys = origin[1] + (np.arange(ny) + 0.5) * cell
    free = ((ys > 0) & (ys < H))[:, None] & ((xs > 0) & (xs < W))[None, :]
    burn_segments(free, WALLS, origin=origin, cell=cell)
    return FloorPlan.from_raster(origin=origin, cell=cell, free=free)


PLAN = fig2_plan()


def links(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return lengths, turns (first 0) and directions of a polyline."""
    d = np.diff(points, axis=0)
    direction = np.arctan2(d[:, 1], d[:, 0])
    return np.hypot(d[:, 0], d[:, 1]), np.r_[0.0, np.diff(direction)], direction


def polyline(start: np.ndarray, lengths: np.ndarray, turns: np.ndarray, heading: float):
    """Dead-reckon the points of a track given as links."""
    direction = heading + np.cumsum(turns)
    steps = lengths[:, None] * np.column_stack([np.cos(direction), np.sin(direction)])
    return np.vstack([start, start + np.cumsum(steps, axis=0)])


def reference_fit(
    plan: FloorPlan,
    start: np.ndarray,
    lengths: np.ndarray,
    turns: np.ndarray,
    heading: float | None,
    p: TrackFitParams,
) -> tuple[np.ndarray, float, list[int], int]:
    """The paper's algorithm written out with loops: points, score, |S_i|, links placed.

    No clearance shortcut, no lazy wall test, no scatter: every candidate is
    sampled and compared key by key.
    """
    scales = sorted(p.scales, key=lambda s: (abs(1.0 - s), s))
    phis = sorted(p.turns, key=lambda q: (abs(q), q))

    def cell(v: np.ndarray) -> tuple[int, int]:
        col, row = np.floor((v - plan.origin) / p.grid).astype(int)
        return int(row), int(col)

    alive = [(0.0, start, 0.0 if heading is None else heading)]
    history: list[list[tuple[int, float, float]]] = []  # per link: (pred row, γ, direction)
    counts: list[int] = []
    for i, length in enumerate(lengths):
        # FloorPlan.segment_free's half-cell sampling, with the step count of
        # the link's longest candidate for every candidate of the link.
        steps = int(np.ceil(max(scales) * length / (0.5 * plan.cell)))
        frac = np.arange(steps + 1) / steps
        if i == 0 and heading is None:
            ks = np.arange(-np.floor(np.pi / p.first_step), np.ceil(np.pi / p.first_step))
            theta = p.first_step * ks
            theta = sorted(theta[(theta >= -np.pi) & (theta < np.pi)], key=lambda t: (abs(t), t))
            options = [(t, 0.0) for t in theta]
        else:
            options = [(turns[i] + q, q) for q in phis]
        new: dict[tuple[int, int], tuple] = {}
        for row, (f, x, psi) in enumerate(alive):
            for gi, gamma in enumerate(scales):
                for ai, (rel, phi) in enumerate(options):
                    theta = psi + rel
                    v = x + gamma * length * np.array([np.cos(theta), np.sin(theta)])
                    if not plan.is_free(x + frac[:, None] * (v - x)).all():
                        continue
                    score = f + (p.c1 * abs(1.0 - gamma) + p.c2 * abs(phi))
                    key = (score, row, gi, ai)
                    c = cell(v)
                    if c not in new or key < new[c][0]:
                        new[c] = (key, v, theta, gamma)
        counts.append(len(new))
        if not new:
            break
        ordered = [new[c] for c in sorted(new)]
        history.append([(key[1], gamma, theta) for key, _, theta, gamma in ordered])
        alive = [(key[0], v, theta) for key, v, theta, _ in ordered]
    j = int(np.argmin([a[0] for a in alive]))
    score = alive[j][0]
    chosen = []
    for step in reversed(history):
        pred, gamma, theta = step[j]
        chosen.append((gamma, theta))
        j = pred
    points = [start]
    for (gamma, theta), length in zip(reversed(chosen), lengths, strict=False):
        points.append(points[-1] + gamma * length * np.array([np.cos(theta), np.sin(theta)]))
    return np.array(points), score, counts, len(history)


def crosses_wall(points: np.ndarray) -> bool:
    """Exact test: does the polyline touch any wall segment?"""
    return bool(shapely.LineString(points).intersects(WALL_LINES))


def test_segments_free_is_the_plans_segment_test() -> None:
    rng = np.random.default_rng(0)
    grid = cell_grid(PLAN, 1.0, 3.0)
    start = PLAN.sample_free(4000, rng)
    angle = rng.uniform(-np.pi, np.pi, 4000)
    end = start + 3.0 * np.column_stack([np.cos(angle), np.sin(angle)])
    inside = PLAN.is_free(end)
    start, end = start[inside], end[inside]
    expected = PLAN.segment_free(start, end)

    def units(x: np.ndarray) -> np.ndarray:
        return (x - PLAN.origin) / PLAN.cell + grid.pad

    # The same half-cell steps as FloorPlan.segment_free takes over this batch.
    steps = np.ceil(np.linalg.norm(end - start, axis=1).max() / (0.5 * PLAN.cell))
    got = segments_free(grid.free, units(start), units(end), 0.5 * steps)
    assert 0.2 < expected.mean() < 0.9  # both outcomes well represented
    np.testing.assert_array_equal(got, expected)


def test_two_disc_bound_never_skips_a_crossing() -> None:
    # A move shorter than safe(start) + max(safe(end), 0) is accepted unsampled:
    # the sampled test must agree on every such move.
    rng = np.random.default_rng(1)
    grid = cell_grid(PLAN, 1.0, 6.0)
    start = PLAN.sample_free(20000, rng)
    angle = rng.uniform(-np.pi, np.pi, start.shape[0])
    length = rng.uniform(0.0, 6.0, start.shape[0])
    end = start + length[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    ok = PLAN.is_free(end)
    start, end, length = start[ok], end[ok], length[ok]

    def safe(x: np.ndarray) -> np.ndarray:
        u = ((x - PLAN.origin) / PLAN.cell + grid.pad).astype(np.int64)
        return grid.safe[u[:, 1] * grid.free.shape[1] + u[:, 0]]

    skipped = length < safe(start) + np.maximum(safe(end), 0.0)
    assert skipped.sum() > 1000
    assert PLAN.segment_free(start[skipped], end[skipped]).all()


def test_best_per_cell_keeps_least_score_then_earliest_and_restores_scratch() -> None:
    grid = cell_grid(PLAN, 1.0, 1.0)
    dest = np.array([5, 3, 5, 3, 7, 3])
    score = np.array([0.2, 0.1, 0.1, 0.1, 0.3, 0.05])
    # cell 3: 0.05 at position 5; cell 5: 0.1 at 2; cell 7: 0.3 at 4
    np.testing.assert_array_equal(best_per_cell(grid, dest, score), [2, 4, 5])
    np.testing.assert_array_equal(best_per_cell(grid, dest[:4], score[:4]), [1, 2])
    assert np.isinf(grid.best).all()
    assert (grid.first == NONE).all()


def test_a_cell_keeps_the_unrotated_link_as_in_fig2() -> None:
    # From (0.1, 0.6) heading east, a 1.5 m link turned by 0, +0.25 or -0.25 rad
    # ends at (1.600, 0.600), (1.553, 0.971) or (1.553, 0.229). DP cells are
    # ⌊(x + 0.45) / 1⌋: column 2 for all, rows 1, 1 and 0. The two links into
    # row 1 meet in one cell and, as in Fig. 2, the unrotated one stays.
    grid = cell_grid(PLAN, 1.0, 1.5)
    turns = np.array([0.0, 0.25, -0.25])
    cost = np.abs(turns)[None, :]
    cells, xi, psi, f, pred, choice = advance(
        grid, np.array([[0.1, 0.6]]), np.zeros(1), np.zeros(1), np.array([1.5]), turns, cost
    )
    nx = grid.nx
    np.testing.assert_array_equal(cells, [0 * nx + 2, 1 * nx + 2])
    np.testing.assert_allclose(f, [0.25, 0.0])
    np.testing.assert_array_equal(choice, [2, 0])
    np.testing.assert_allclose(psi, [-0.25, 0.0])
    np.testing.assert_allclose(
        xi, [[0.1 + 1.5 * np.cos(0.25), 0.6 - 1.5 * np.sin(0.25)], [1.6, 0.6]]
    )
    np.testing.assert_array_equal(pred, [0, 0])


def test_rival_links_into_one_cell_keep_the_cheaper() -> None:
    # Two tracks whose next links end in the same cell: the cheaper survives;
    # on equal scores the one from the lower row.
    grid = cell_grid(PLAN, 1.0, 1.0)
    xi = np.array([[1.1, 1.0], [1.1, 1.2]])
    cells, _, _, f, pred, _ = advance(
        grid, xi, np.zeros(2), np.array([0.3, 0.1]), np.array([1.0]), np.zeros(1), np.zeros((1, 1))
    )
    assert cells.size == 1 and pred[0] == 1 and f[0] == pytest.approx(0.1)
    cells, _, _, f, pred, _ = advance(
        grid, xi, np.zeros(2), np.array([0.1, 0.1]), np.array([1.0]), np.zeros(1), np.zeros((1, 1))
    )
    assert cells.size == 1 and pred[0] == 0


def random_walk(rng: np.random.Generator, n: int) -> np.ndarray:
    """A walk of n links of 1-2 m on the Fig. 2 plan, turning by right angles now and then."""
    points = [np.array([rng.uniform(1.0, 11.0), 1.0])]
    direction = rng.choice([0.0, np.pi])
    while len(points) <= n:
        turn = rng.choice([0.0, 0.0, np.pi / 2, -np.pi / 2, np.pi]) + rng.normal(0.0, 0.1)
        end = points[-1] + rng.uniform(1.0, 2.0) * np.array(
            [np.cos(direction + turn), np.sin(direction + turn)]
        )
        if PLAN.clearance_at(end) >= 0.4 and PLAN.segment_free(points[-1][None], end[None])[0]:
            points.append(end)
            direction += turn
    return np.array(points)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("known_heading", [True, False])
@pytest.mark.parametrize("grid", [1.0, 0.5])
def test_fit_equals_the_loop_reference(seed: int, known_heading: bool, grid: float) -> None:
    rng = np.random.default_rng(seed)
    truth = random_walk(rng, 10)
    lengths, turns, direction = links(truth)
    # Phone-like errors: lengths off by up to 10 %, turns and heading by ~3°.
    lengths *= rng.uniform(0.9, 1.1, lengths.size)
    turns += rng.normal(0.0, 0.05, turns.size)
    heading = float(direction[0] + rng.normal(0.0, 0.05)) if known_heading else None
    # The paper's algorithm: a link no track survives ends the fit.
    params = TrackFitParams(grid=grid, first_step=0.1, recover=False, cell_per_link=0.0)
    fit = fit_track(PLAN, truth[0], lengths, turns, heading=heading, params=params)
    points, score, counts, placed = reference_fit(PLAN, truth[0], lengths, turns, heading, params)
    assert fit.alive.tolist() == counts
    assert fit.points.shape[0] == placed + 1
    assert (fit.failed is None) == (placed == lengths.size)
    np.testing.assert_allclose(fit.points, points, atol=1e-9)
    assert fit.score == pytest.approx(score, abs=1e-12)


def test_track_that_fits_is_returned_unchanged_with_score_zero() -> None:
    lengths, turns, direction = links(ROUTE)
    fit = fit_track(PLAN, ROUTE[0], lengths, turns, heading=float(direction[0]))
    assert fit.failed is None
    assert fit.score == 0.0
    np.testing.assert_allclose(fit.points, ROUTE, atol=1e-9)
    np.testing.assert_array_equal(fit.scale, np.ones(lengths.size))
    np.testing.assert_array_equal(fit.turn, np.zeros(lengths.size))


def test_unknown_heading_finds_a_rigid_rotation_with_score_zero() -> None:
    lengths, turns, _ = links(ROUTE)
    fit = fit_track(PLAN, ROUTE[0], lengths, turns)
    assert fit.failed is None
    assert fit.score == 0.0
    assert np.isnan(fit.turn[0]) and (fit.turn[1:] == 0.0).all()
    np.testing.assert_array_equal(fit.scale, np.ones(lengths.size))
    # Same shape: the fitted polyline is the input turned about the start.
    rotated = polyline(ROUTE[0], lengths, turns, float(fit.direction[0]))
    np.testing.assert_allclose(fit.points, rotated, atol=1e-9)
    assert not crosses_wall(fit.points)


def test_fit_avoids_the_wall_the_raw_track_crosses() -> None:
    lengths, turns, direction = links(ROUTE)
    # The phone under-measures every step by 10 %: turning north 0.7 m early
    # puts the raw track through the wall left of the door.
    raw = polyline(ROUTE[0], lengths / 1.1, turns, float(direction[0]))
    assert crosses_wall(raw)
    assert not PLAN.segment_free(raw[:-1], raw[1:]).all()
    fit = fit_track(PLAN, ROUTE[0], lengths / 1.1, turns)
    assert fit.failed is None
    assert not crosses_wall(fit.points)
    assert PLAN.segment_free(fit.points[:-1], fit.points[1:]).all()
    # It went through the door into the right-hand room.
    assert fit.points[-1, 1] > 2.0 and fit.points[-1, 0] > 6.0
    assert np.linalg.norm(fit.points - ROUTE, axis=1).max() < 1.0


def staircase(cell: float = 0.05, width: float = 0.6) -> tuple[FloorPlan, np.ndarray]:
    """A corridor ``width`` wide turning left, right, left: every turn point is pinned."""
    corners = np.array([[1, 1], [7.6, 1], [7.6, 7.6], [14.2, 7.6], [14.2, 14.2]], dtype=float)
    area = shapely.LineString(corners).buffer(width / 2, cap_style="square", join_style="mitre")
    origin = np.array([-0.02, -0.02])
    n = round(16.0 / cell)
    centres = origin[0] + (np.arange(n) + 0.5) * cell
    gx, gy = np.meshgrid(centres, centres)
    free = shapely.contains_xy(area, gx, gy)
    return FloorPlan.from_raster(origin=origin, cell=cell, free=free), corners


def test_known_scale_and_heading_bias_are_recovered() -> None:
    # The phone measured every link 1/1.1 of its length and started 0.05 rad
    # (one Φ step) clockwise of the truth. In a 0.6 m corridor a link ending
    # 0.6 m short puts the next one into the wall, and an uncorrected 0.05 rad
    # drifts 0.33 m sideways over the first 6.6 m link: the only fit of score
    # 3 × 0.1 + 0.05 stretches the first three links by 1.1 and turns the first
    # back by 0.05; the last link, pinned by nothing, keeps its measured length.
    # (An exhaustive search of all 3⁴ × 11⁴ choices confirms 0.35 is the
    # unique minimum, the runner-up scoring 0.40.)
    plan, corners = staircase()
    lengths, turns, _ = links(corners)
    fit = fit_track(
        plan, corners[0], lengths / 1.1, turns, heading=-0.05, params=TrackFitParams(grid=0.5)
    )
    assert fit.failed is None
    assert fit.score == pytest.approx(0.35, abs=1e-12)
    np.testing.assert_allclose(fit.scale, [1.1, 1.1, 1.1, 1.0])
    np.testing.assert_allclose(fit.turn, [0.05, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(fit.points[:4], corners[:4], atol=1e-9)
    np.testing.assert_allclose(fit.points[4], corners[3] + [0.0, 6.0], atol=1e-9)


def test_choice_order_does_not_change_the_fit() -> None:
    lengths, turns, _ = links(ROUTE)
    base = fit_track(PLAN, ROUTE[0], lengths / 1.1, turns)
    shuffled = TrackFitParams(
        scales=(1.1, 0.9, 1.0), turns=tuple(np.random.default_rng(2).permutation(base_turns()))
    )
    again = fit_track(PLAN, ROUTE[0], lengths / 1.1, turns, params=shuffled)
    np.testing.assert_array_equal(again.points, base.points)
    assert again.score == base.score


def base_turns() -> tuple[float, ...]:
    return TrackFitParams().turns


def test_failures_return_the_best_partial_track() -> None:
    # A 20 m link fits nowhere in a 12 × 8 m plan; without recovery the fit stops there.
    strict = TrackFitParams(recover=False, snap_start=0.0)
    fit = fit_track(PLAN, ROUTE[0], np.array([1.5, 20.0]), np.zeros(2), heading=0.0, params=strict)
    assert fit.failed == "no track survives link 2 of 2"
    np.testing.assert_allclose(fit.points, ROUTE[:2], atol=1e-9)
    assert fit.alive.tolist()[-1] == 0

    blocked = fit_track(PLAN, np.array([5.0, 2.0]), np.ones(2), np.zeros(2), params=strict)
    assert blocked.failed == "start is not in free space"
    assert blocked.points.shape == (1, 2)

    ticks = itertools.count()
    lengths, turns, direction = links(ROUTE)
    slow = fit_track(
        PLAN,
        ROUTE[0],
        lengths,
        turns,
        heading=float(direction[0]),
        params=TrackFitParams(time_limit_s=1.5),
        clock=lambda: float(next(ticks)),
    )
    assert slow.failed == "time limit of 1.5 s reached after link 2 of 8"
    np.testing.assert_allclose(slow.points, ROUTE[:3], atol=1e-9)


def test_invalid_input_is_rejected() -> None:
    with pytest.raises(ValueError):
        fit_track(PLAN, ROUTE[0], np.ones(3), np.zeros(2))
    with pytest.raises(ValueError):
        fit_track(PLAN, ROUTE[0], np.array([1.0, -1.0]), np.zeros(2))
    with pytest.raises(ValueError):
        fit_track(PLAN, ROUTE[0], np.ones(2), np.zeros(2), params=TrackFitParams(grid=0.0))


def test_blocked_start_is_snapped_to_the_nearest_free_cell() -> None:
    # (5, 2) lies on the corridor wall: a surveyed or radio start a hair inside
    # a barrier. The fitter moves it to the nearest free raster cell and fits
    # from there, reporting the move; beyond snap_start it refuses as before.
    start = np.array([5.0, 2.0])
    lengths, turns = np.array([2.0, 2.0]), np.array([0.0, 0.0])
    fit = fit_track(PLAN, start, lengths, turns, heading=0.0)
    assert fit.failed is None
    assert bool(PLAN.is_free(fit.points[0]))
    assert 0.0 < fit.start_shift < PLAN.cell
    np.testing.assert_allclose(np.linalg.norm(fit.points[0] - start), fit.start_shift)
    refused = fit_track(
        PLAN, start, lengths, turns, heading=0.0, params=TrackFitParams(snap_start=0.0)
    )
    assert refused.failed == "start is not in free space"


def test_dead_link_is_placed_with_the_wider_turns() -> None:
    # The staircase corridor, 0.6 m wide, with the first corner's turn measured
    # 0.45 rad short: no φ of Φ (±0.25) gets the second link into the corridor
    # going north, so the paper's fit dies there; Φ_w (±0.5) places it with
    # φ = 0.45 and the rest of the track fits as measured.
    plan, corners = staircase()
    lengths, turns, _ = links(corners)
    turns[1] -= 0.45
    strict = fit_track(
        plan, corners[0], lengths, turns, heading=0.0, params=TrackFitParams(recover=False)
    )
    assert strict.failed == "no track survives link 2 of 4"
    fit = fit_track(plan, corners[0], lengths, turns, heading=0.0)
    assert fit.failed is None
    assert fit.relaxed.tolist() == [RELAX_NONE, RELAX_WIDENED, RELAX_NONE, RELAX_NONE]
    assert fit.turn[1] == pytest.approx(0.45)
    assert fit.score == pytest.approx(0.45)
    np.testing.assert_allclose(fit.points, corners, atol=1e-9)


def test_link_through_a_wall_is_kept_when_nothing_else_fits() -> None:
    # The walker went north from the corridor into the left room at x = 5,
    # where the plan has a wall and no door (a door missing from the map). Every
    # candidate, even with Γ_w and Φ_w, crosses it; the link is placed as
    # measured and flagged, and the fit continues inside the room; the crossing
    # costs its penalty, so a rotation that needs none would score better.
    fit = fit_track(
        PLAN, np.array([5.0, 1.0]), np.array([2.0, 2.0]), np.zeros(2), heading=np.pi / 2
    )
    assert fit.failed is None
    assert fit.relaxed.tolist() == [RELAX_CROSSED, RELAX_NONE]
    np.testing.assert_allclose(fit.points, [[5.0, 1.0], [5.0, 3.0], [5.0, 5.0]], atol=1e-9)
    assert fit.score == TrackFitParams().cross_cost


def test_links_ending_inside_a_barrier_are_dead_reckoned_until_free_again() -> None:
    # A 20 × 4 m corridor with a barrier across it at 9 < x < 11 that the walker
    # went straight through (an open area the map closes). From x = 8.5 every
    # candidate of the next link ends inside it, so links 8 and 9 keep their
    # measured length and turn; link 10 leaves it crossing its edge, with a
    # free end; then the fit goes on as usual. Off the raster nothing is placed.
    cell = 0.1
    origin = np.array([-0.45, -0.45])
    xs = origin[0] + (np.arange(round(21 / cell)) + 0.5) * cell
    ys = origin[1] + (np.arange(round(5 / cell)) + 0.5) * cell
    free = ((ys > 0) & (ys < 4))[:, None] & ((xs > 0) & (xs < 20) & ~((xs > 9) & (xs < 11)))
    plan = FloorPlan.from_raster(origin=origin, cell=cell, free=free)
    start = np.array([1.5, 2.0])
    fit = fit_track(plan, start, np.ones(11), np.zeros(11), heading=0.0)
    assert fit.failed is None
    assert fit.relaxed.tolist() == [RELAX_NONE] * 7 + [
        RELAX_DEAD_RECKONED,
        RELAX_DEAD_RECKONED,
        RELAX_CROSSED,
        RELAX_NONE,
    ]
    np.testing.assert_allclose(fit.points[:, 0], 1.5 + np.arange(12), atol=1e-9)
    np.testing.assert_allclose(fit.points[:, 1], 2.0, atol=1e-9)
    p = TrackFitParams()
    assert fit.score == pytest.approx(2 * p.reckon_cost + p.cross_cost)
    off = fit_track(plan, start, np.array([30.0]), np.zeros(1), heading=0.0)
    assert off.failed == "no track survives link 1 of 1"


def test_links_shorter_than_the_grid_get_cells_no_larger_than_a_link() -> None:
    # ROUTE walked in 0.5 m steps, each measured 10 % short. With 1 m cells two
    # consecutive steps mostly end in one cell, where only the cheapest track
    # (unstretched, heading for the wall left of the door) survives: at most two
    # cells stay alive and the paper's fit dies before the door. Cells of one
    # step keep the stretched alternatives and the fit goes through the door.
    dense = [ROUTE[0]]
    for a, b in itertools.pairwise(ROUTE):
        n = int(np.ceil(np.linalg.norm(b - a) / 0.5))
        dense += [a + (b - a) * k / n for k in range(1, n + 1)]
    lengths, turns, direction = links(np.array(dense))
    heading = float(direction[0])
    coarse = TrackFitParams(cell_per_link=0.0, recover=False)
    stuck = fit_track(PLAN, dense[0], lengths / 1.1, turns, heading=heading, params=coarse)
    assert stuck.failed is not None and stuck.alive.max() <= 2
    fit = fit_track(
        PLAN, dense[0], lengths / 1.1, turns, heading=heading, params=TrackFitParams(recover=False)
    )
    assert fit.failed is None
    assert stuck.cell == 1.0
    assert fit.cell == pytest.approx(np.median(lengths / 1.1))
    assert fit.alive.max() > 2
    assert PLAN.segment_free(fit.points[:-1], fit.points[1:]).all()
    assert fit.points[-1, 0] > 6.0 and fit.points[-1, 1] > 2.0


def test_spread_measures_how_far_equally_good_fits_end_apart() -> None:
    # Three straight 1.5 m links from the middle of the corridor. Known heading
    # (east): one way to fit, the near-best tracks end within a Φ step's swing.
    # Unknown heading: east and west fit equally well (score 0), 9 m apart.
    start = np.array([6.0, 1.0])
    lengths, turns = np.full(3, 1.5), np.zeros(3)
    known = fit_track(PLAN, start, lengths, turns, heading=0.0)
    assert known.spread < 0.5
    free = fit_track(PLAN, start, lengths, turns)
    assert free.score == 0.0
    assert free.spread == pytest.approx(9.0, abs=0.5)
