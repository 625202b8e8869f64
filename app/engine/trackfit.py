"""Fit a dead-reckoned track to the floor plan by dynamic programming (seed 004).

A device in energy-saving mode uploads its own dead-reckoned track as links:
a length l_i and the turn from the previous link. Step lengths are off by up
to about 10 % and headings by a few degrees, so the raw polyline crosses
walls. Following Voronov et al., the fitter searches the tracks obtained by
scaling each link by γ ∈ Γ and changing each turn by φ ∈ Φ, rejects those with
a link through a wall, a barrier or the outline, and returns the one that
changed the input least:

    f = C1 Σ |1 - γ_i| + C2 Σ |φ_i|.

The search is the paper's approximate dynamic programme. The plan is cut
into square cells S and, for every link i and cell s, only the best track of
the first i links ending in s survives: its score f_i(s), end point ξ_i(s),
direction ψ_i(s) and predecessor cell ζ_i(s). A backward pass from the best
final cell gives the fitted points. Only reachable free cells are ever alive,
so a link costs O(|S_i| |Γ| |Φ|) with |S_i| the cells the first i links can
reach, bounded by the walkable area divided by the cell area.

Two departures from the paper, both for real phone tracks (site1): the DP
cell shrinks to the median link length when links are shorter than the grid
(``cell_per_link``; per-step links otherwise leave the DP one track per cell
and it turns greedy), and a link no track survives is not the end of the fit:
it is placed by a recovery ladder (wider Γ_w and Φ_w; then crossing a wall
with a free end, for doors the map lacks; then dead reckoning, for walkers
where the map says nobody can be) and flagged in ``TrackFit.relaxed``.
``recover=False, cell_per_link=0`` is the paper's algorithm.

Walls are tested on the ``FloorPlan`` raster: a candidate link ending on a
blocked cell is dropped by one gather; a link shorter than the clearance at
its start (less the raster's cell diagonal) cannot cross anything; only the
remaining links are sampled with ``FloorPlan.segment_free``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from app.engine.plan import FloorPlan


@dataclass(frozen=True)
class TrackFitParams:
    """Tunable constants of the track fitter (defaults from seed 004).

    Attributes
    ----------
    grid : float
        Side (m) of the square cells S of the dynamic programme; the paper
        uses 1 m. Finer cells keep more tracks alive: closer to the exact
        optimum, slower.
    scales : tuple of float
        Γ, the factors a link's length may be multiplied by.
    turns : tuple of float
        Φ (rad), the changes a turn between two links may receive.
    first_step : float
        Step (rad) of the directions tried for the first link over [-π, π)
        when the initial heading is unknown.
    c1 : float
        C1, weight of the length changes Σ |1 - γ_i|.
    cell_per_link : float
        The DP cell is at most this many median link lengths (and at least one
        raster cell); 0 keeps ``grid`` whatever the links. A link shorter than
        the cell mostly ends in the cell it started from, where only the
        cheapest track survives: the DP keeps one or two tracks and turns
        greedy (on site1 per-step links of 0.66 m at a 1 m grid kept 1-8 cells
        alive and died at a wall in 70 of 114 test walks). The paper's 1 m grid
        suits its links of a metre or more; for shorter links the cell shrinks
        with them, at the cost of more cells alive. On the site1 validation
        walks (per-step links, heading known) the mean error was 4.57 m at 0
        (raw 3.41 m), 3.61 m at 1, 3.15 m at 1/√2 (the cell whose diagonal is
        a link, which every link leaves); 1/√2 costs about 2.5 times the time
        and takes a 171-step track on the largest floor past the 1 s budget,
        so the default is 1.
    c2 : float
        C2, weight of the turn changes Σ |φ_i|.
    recover : bool
        When no track survives a link, place it by the recovery ladder rather
        than give up (see ``RELAX_*``).
    wide_scales, wide_turns : tuple of float
        Γ_w and Φ_w (rad), the first rung of that ladder, costed by the same
        C1 |1 - γ| + C2 |φ|. Physical range: on the ILC site1 training walks the
        PDR's length over the surveyed length between waypoints runs 0.82–1.24
        (10th–90th percentile) and its heading, after removing each walk's
        bias, strays up to 22° (90th percentile) between waypoints: Γ_w =
        0.7–1.3 and Φ_w = ±0.5 rad (29°) cover that, Γ and Φ do not.
    snap_start : float
        Largest distance (m) a start on a blocked cell is moved to the nearest
        free cell; 0 refuses such a start.
    spread_margin : float
        Score margin of the tracks ``TrackFit.spread`` measures (one Φ step).
    time_limit_s : float
        The forward pass gives up (``failed``) after this much computing time (s).
    """

    grid: float = 1.0
    scales: tuple[float, ...] = (0.9, 1.0, 1.1)
    turns: tuple[float, ...] = (
        -0.25,
        -0.20,
        -0.15,
        -0.10,
        -0.05,
        0.0,
        0.05,
        0.10,
        0.15,
        0.20,
        0.25,
    )
    first_step: float = 0.05
    cell_per_link: float = 1.0
    c1: float = 1.0
    c2: float = 1.0
    recover: bool = True
    wide_scales: tuple[float, ...] = (0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3)
    wide_turns: tuple[float, ...] = tuple(round(0.05 * k, 2) for k in range(-10, 11))
    snap_start: float = 2.0
    spread_margin: float = 0.05
    time_limit_s: float = 10.0


@dataclass(frozen=True)
class TrackFit:
    """Result of a fit.

    Attributes
    ----------
    points : ndarray, shape (k + 1, 2)
        Fitted points x_0 … x_k (m); k = n links on success, on failure the
        best fit of the links that could still be placed.
    score : float
        f of the fitted track (of its k links).
    scale : ndarray, shape (k,)
        γ chosen for each link.
    turn : ndarray, shape (k,)
        φ (rad) added to each turn; NaN for the first link when the heading
        was unknown (its direction was searched freely).
    direction : ndarray, shape (k,)
        Direction of each fitted link (rad, counter-clockwise from +x).
    alive : ndarray of int, shape (m,)
        |S_i|, the cells holding a track after each link processed.
    failed : str or None
        Why no complete track was found; None on success.
    relaxed : ndarray of int8, shape (k,)
        How each link was placed: ``RELAX_NONE`` normally, else the rung of
        the recovery ladder that placed it.
    start_shift : float
        Distance (m) the start was moved off a blocked cell.
    cell : float
        Side (m) of the DP cells used: ``grid``, or less for short links
        (``cell_per_link``).
    spread : float
        Largest distance (m) from the fitted last point to the last point of
        any other surviving track scoring within ``spread_margin`` of it. The
        score cannot tell those tracks apart: a large spread (typically with
        the heading unknown in open halls, where any rotation fits) says the
        plan did not determine the fit.
    """

    points: np.ndarray
    score: float
    scale: np.ndarray
    turn: np.ndarray
    direction: np.ndarray
    alive: np.ndarray
    failed: str | None = None
    relaxed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int8))
    start_shift: float = 0.0
    spread: float = 0.0
    cell: float = 0.0


@dataclass(frozen=True)
class CellGrid:
    """The DP cells over the plan and the wall-test lookups derived from its raster.

    Raster lookups work in padded raster units ``u = (x - origin) / rcell +
    pad``: the raster gets ``pad`` blocked cells on every side, more than the
    longest move, so every candidate end point indexes the arrays without a
    bounds test. ``best``, ``first`` and ``mark`` are per-DP-cell scratch
    arrays of ``advance``, +inf, ``NONE`` and False between calls: resetting
    only the touched cells keeps a link's cost independent of the floor's size.
    """

    origin: np.ndarray
    """x, y (m) of the lower-left corner of the plan's raster."""
    cell: float
    """DP cell side (m)."""
    nx: int
    ny: int
    rcell: float
    """Raster cell side (m)."""
    pad: int
    free: np.ndarray = field(repr=False)
    """Padded free raster, bool (ny_r + 2 pad, nx_r + 2 pad)."""
    safe: np.ndarray = field(repr=False)
    """Flat over the padded raster (m): no point of a blocked cell lies closer
    than this to any point of the cell (may be negative)."""
    safe_end: np.ndarray = field(repr=False)
    """``max(safe, 0)``, flat."""
    best: np.ndarray = field(repr=False)
    first: np.ndarray = field(repr=False)
    mark: np.ndarray = field(repr=False)


NONE = np.iinfo(np.int64).max
"""Empty slot of ``CellGrid.first``."""

MAX_SAMPLES = 1 << 21
"""Largest number of raster samples one wall-test chunk holds in memory."""


def cell_grid(plan: FloorPlan, cell: float, reach: float) -> CellGrid:
    """Lay DP cells of side ``cell`` (m) over the plan for moves up to ``reach`` (m) long."""
    ny_r, nx_r = plan.shape
    free = plan.free
    border = np.r_[free[0], free[-1], free[:, 0], free[:, -1]]
    if border.any():
        # A free cell on the raster's edge is next to "outside", which the
        # plan's clearance does not see: measure it on a blocked-padded copy.
        clearance = ndimage.distance_transform_edt(np.pad(free, 1))[1:-1, 1:-1] * plan.cell
    else:
        clearance = plan.clearance
    # Any point of a blocked cell is at least D - √2·cell from any point of a
    # cell whose centre is D from that blocked cell's centre.
    safe = np.asarray(clearance, dtype=np.float32) - np.float32(np.sqrt(2.0) * plan.cell)
    pad = int(np.ceil(reach / plan.cell)) + 2
    safe = np.pad(safe, pad, constant_values=-np.inf).ravel()
    nx = int(np.ceil(nx_r * plan.cell / cell))
    ny = int(np.ceil(ny_r * plan.cell / cell))
    return CellGrid(
        origin=np.asarray(plan.origin, dtype=float),
        cell=float(cell),
        nx=nx,
        ny=ny,
        rcell=float(plan.cell),
        pad=pad,
        free=np.pad(free, pad, constant_values=False),
        safe=safe,
        safe_end=np.maximum(safe, np.float32(0.0)),
        best=np.full(nx * ny, np.inf),
        first=np.full(nx * ny, NONE, dtype=np.int64),
        mark=np.zeros(nx * ny, dtype=bool),
    )


def segments_free(
    free: np.ndarray, start: np.ndarray, end: np.ndarray, max_len: float
) -> np.ndarray:
    """Return whether each straight move between raster coordinates stays on free cells.

    The same test as ``FloorPlan.segment_free`` (samples every half cell,
    which supercover-burnt walls cannot slip between), on coordinates already
    in raster units and known to lie in the raster, without the end points
    (known free), in chunks of bounded memory.

    Parameters
    ----------
    free : ndarray of bool, shape (ny, nx)
        Free raster.
    start, end : ndarray, shape (m, 2)
        Move ends in raster units (column, row as floats, non-negative).
    max_len : float
        Upper bound of the move lengths (raster cells).

    Returns
    -------
    ndarray of bool, shape (m,)
    """
    nx = free.shape[1]
    flat = free.ravel()
    steps = max(1, int(np.ceil(max_len / 0.5)))
    # interior sample fractions k / steps, k = 1 … steps - 1
    frac = np.arange(1, steps) / steps
    out = np.ones(start.shape[0], dtype=bool)
    if frac.size == 0:
        return out
    chunk = max(1, MAX_SAMPLES // frac.size)
    for lo in range(0, start.shape[0], chunk):
        a, b = start[lo : lo + chunk], end[lo : lo + chunk]
        # u = a + k/steps (b - a)
        col = (a[:, 0] + frac[:, None] * (b[:, 0] - a[:, 0])).astype(np.int64)
        row = (a[:, 1] + frac[:, None] * (b[:, 1] - a[:, 1])).astype(np.int64)
        out[lo : lo + chunk] = flat[row * nx + col].all(axis=0)
    return out


def _ordered(values: tuple[float, ...], centre: float) -> np.ndarray:
    """Return the values sorted by distance from ``centre`` then value: ties prefer less change."""
    arr = np.asarray(values, dtype=float)
    return arr[np.lexsort((arr, np.abs(arr - centre)))]


def best_per_cell(grid: CellGrid, dest: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Return the position of the least-score entry of each destination cell.

    Of equal scores the earliest entry wins.

    Parameters
    ----------
    grid : CellGrid
        Supplies the scratch arrays (left as found).
    dest : ndarray of int64, shape (M,)
        Flat DP cell of each entry.
    score : ndarray, shape (M,)
        Score of each entry.

    Returns
    -------
    ndarray of int64, shape (C,)
        One position into the inputs per distinct cell, increasing.
    """
    best, first = grid.best, grid.first
    # best(s) = min score over entries into s, by an unbuffered scatter-min
    np.minimum.at(best, dest, score)
    tie = np.flatnonzero(score == best[dest])
    np.minimum.at(first, dest[tie], tie)
    won = tie[first[dest[tie]] == tie]
    best[dest] = np.inf
    first[dest] = NONE
    return won


def advance(
    grid: CellGrid,
    xi: np.ndarray,
    psi: np.ndarray,
    f: np.ndarray,
    lengths: np.ndarray,
    rel: np.ndarray,
    cost: np.ndarray,
    *,
    free_end: bool = True,
    walls: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Extend every surviving track by one link and keep the best per destination cell.

    Parameters
    ----------
    grid : CellGrid
        The DP cells, wall-test lookups and scratch arrays, from ``cell_grid``.
    xi : ndarray, shape (K, 2)
        End points ξ (m) of the K surviving tracks, on free cells.
    psi : ndarray, shape (K,)
        Direction ψ (rad) of their last link.
    f : ndarray, shape (K,)
        Their scores.
    lengths : ndarray, shape (G,)
        Candidate lengths γ l_i (m) of the new link, at most the grid's reach.
    rel : ndarray, shape (A,)
        Candidate directions of the new link relative to ψ (rad).
    cost : ndarray, shape (G, A)
        Score added by each (length, direction) choice.
    free_end : bool
        Drop candidates ending on a blocked raster cell. Without it (the last
        resort of a dead link) only ends off the raster are dropped.
    walls : bool
        Drop candidates whose move crosses a blocked cell.

    Returns
    -------
    cells : ndarray of int64, shape (K',)
        Flat DP cells (row-major) holding a track after the link, increasing.
    xi, psi, f : ndarray, shapes (K', 2), (K',), (K',)
        End point, direction and score of the best track in each.
    pred : ndarray of int64, shape (K',)
        Row in the input arrays of each track's predecessor.
    choice : ndarray of int64, shape (K',)
        Chosen candidate ``g * A + a``.

    Notes
    -----
    Of equal scores the candidate with the lowest (predecessor row, g, a)
    wins, so results do not depend on summation or scatter order.
    """
    n_a = cost.shape[1]
    nxp = grid.free.shape[1]
    # θ = ψ + rel
    ang = psi[:, None] + rel[None, :]
    cos, sin = np.cos(ang), np.sin(ang)
    # u₀ = (ξ - origin) / cell + pad, the start in padded raster units
    u0 = (xi - grid.origin) / grid.rcell + grid.pad
    step = lengths / grid.rcell
    # v = ξ + γ l (cos θ, sin θ), candidates laid out (K, G, A)
    ux = step[None, :, None] * cos[:, None, :]
    ux += u0[:, 0, None, None]
    uy = step[None, :, None] * sin[:, None, :]
    uy += u0[:, 1, None, None]
    # Raster cell of v (non-negative thanks to the padding, so truncation is ⌊u⌋).
    cell = uy.astype(np.int64)
    cell *= nxp
    cell += ux.astype(np.int64)
    if free_end:
        ok = grid.free.ravel()[cell]
    else:
        # Anywhere on the raster (so later moves stay in the padding): nobody
        # walks off the floor plan's extent.
        ny_r, nx_r = grid.free.shape[0] - 2 * grid.pad, nxp - 2 * grid.pad
        ok = (ux >= grid.pad) & (ux < grid.pad + nx_r) & (uy >= grid.pad) & (uy < grid.pad + ny_r)
    # C order: position in the surviving list increases with (k, g, a).
    k, g, a = np.nonzero(ok)
    cell, ux, uy = cell[ok], ux[ok], uy[ok]

    # f_i = f_{i-1}(σ) + C1 |1 - γ| + C2 |φ|
    score = f[k] + cost[g, a]
    # DP cell of v: ⌊(u - pad) rcell / cell⌋
    ratio = grid.rcell / grid.cell
    dest = ((uy - grid.pad) * ratio).astype(np.int64) * grid.nx
    dest += ((ux - grid.pad) * ratio).astype(np.int64)

    # Two free discs, radius safe(ξ) around the start and safe(v) around the
    # end, cover the move when γ l < safe(ξ) + max(safe(v), 0): no sampling.
    c0 = u0.astype(np.int64)
    safe0 = grid.safe[c0[:, 1] * nxp + c0[:, 0]]
    needs = lengths[g] >= safe0[k] + grid.safe_end[cell]
    if not walls:
        needs[:] = False

    def clear(pos: np.ndarray) -> np.ndarray:
        """Sampled wall test of the candidates at positions ``pos``."""
        end = np.column_stack([ux[pos], uy[pos]])
        return segments_free(grid.free, u0[k[pos]], end, float(step.max()))

    # Sampling only the winners first gives the same result as sampling every
    # candidate: a cell whose winner proves clear keeps it, and only the cells
    # whose winner crosses a wall are decided again, all their moves sampled.
    won = best_per_cell(grid, dest, score)
    test = won[needs[won]]
    bad = test[~clear(test)]
    if bad.size:
        grid.mark[dest[bad]] = True
        sub = np.flatnonzero(grid.mark[dest])
        grid.mark[dest[bad]] = False
        crossed = np.zeros(score.size, dtype=bool)
        recheck = sub[needs[sub]]
        crossed[recheck] = ~clear(recheck)
        sub = sub[~crossed[sub]]
        dropped = np.zeros(score.size, dtype=bool)
        dropped[bad] = True
        won = np.concatenate([won[~dropped[won]], sub[best_per_cell(grid, dest[sub], score[sub])]])
    won = won[np.argsort(dest[won])]

    pred = k[won]
    return (
        dest[won],
        grid.origin + grid.rcell * (np.column_stack([ux[won], uy[won]]) - grid.pad),
        ang[pred, a[won]],
        score[won],
        pred,
        g[won] * n_a + a[won],
    )


@dataclass(frozen=True)
class LinkOptions:
    """The candidates tried for one link: γ values, directions relative to ψ, their φ and cost."""

    scales: np.ndarray
    rel: np.ndarray
    phi: np.ndarray
    cost: np.ndarray


def _replay(
    start: np.ndarray,
    psi0: float,
    lengths: np.ndarray,
    options: list[LinkOptions],
    choices: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rebuild points, chosen γ, φ and directions from the per-link choices ``g * A + a``."""
    k = choices.size
    points = np.empty((k + 1, 2))
    points[0] = start
    direction = np.empty(k)
    gamma = np.empty(k)
    phi = np.empty(k)
    psi = psi0
    for i in range(k):
        opt = options[i]
        g, a = divmod(int(choices[i]), opt.rel.size)
        # ψ_i = ψ_{i-1} + turn_i + φ_i,  x_i = x_{i-1} + γ l_i (cos ψ_i, sin ψ_i)
        psi = psi + opt.rel[a]
        step = lengths[i] * opt.scales[g]
        points[i + 1] = points[i] + step * np.array([np.cos(psi), np.sin(psi)])
        direction[i] = psi
        gamma[i] = opt.scales[g]
        phi[i] = opt.phi[a]
    return points, gamma, phi, direction


RELAX_NONE = 0
"""The link was placed with Γ and Φ, clear of every wall."""
RELAX_WIDENED = 1
"""No track survived the link with Γ and Φ: it was placed with the wider Γ_w and Φ_w."""
RELAX_CROSSED = 2
"""Not even Γ_w and Φ_w placed it: the link crosses a wall (Γ, Φ; its end is free)."""
RELAX_DEAD_RECKONED = 3
"""No candidate even ended on free space (the walker is where the plan says nobody
can be): the link keeps its measured length and turn, walls ignored; only an
end off the plan's raster is refused (then the fit fails at that link)."""


def fit_track(
    plan: FloorPlan,
    start: np.ndarray,
    lengths: np.ndarray,
    turns: np.ndarray,
    *,
    heading: float | None = None,
    params: TrackFitParams | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> TrackFit:
    """Fit a track given as links to the plan, starting at ``start``.

    Parameters
    ----------
    plan : FloorPlan
        Free space; no fitted link crosses a blocked raster cell.
    start : ndarray, shape (2,)
        x_0 (m), the first point of the track. A start on a blocked cell (a
        surveyed or radio fix a little inside a barrier) is moved to the
        nearest free cell's centre when that is within ``params.snap_start``.
    lengths : ndarray, shape (n,)
        Link lengths l_i (m), non-negative.
    turns : ndarray, shape (n,)
        Turn (rad, counter-clockwise positive) from the previous link to link
        i; ``turns[0]`` is the turn from ``heading`` and ignored without one.
    heading : float, optional
        Direction (rad, counter-clockwise from +x) before the first link. When
        None, the first link tries every direction of [-π, π) in steps of
        ``first_step`` at no cost, as in the paper.
    params : TrackFitParams, optional
        Γ, Φ, grid, weights, recovery sets and time limit.
    clock : callable
        Seconds counter used for the time limit.

    Returns
    -------
    TrackFit
        The fitted track. A link no track survives is placed by the recovery
        steps of ``TrackFit.relaxed`` (with ``params.recover``); ``failed``
        is set, with the best partial track, when the start is blocked beyond
        ``snap_start``, a link dies without recovery, or time runs out.
    """
    p = params or TrackFitParams()
    t0 = clock()
    start = np.asarray(start, dtype=float).reshape(2)
    lengths = np.asarray(lengths, dtype=float).reshape(-1)
    turns = np.asarray(turns, dtype=float).reshape(-1)
    if lengths.shape != turns.shape:
        raise ValueError("lengths and turns must have the same length")
    if not (np.all(np.isfinite(lengths)) and np.all(lengths >= 0) and np.all(np.isfinite(turns))):
        raise ValueError("lengths must be finite and non-negative, turns finite")
    if p.grid <= 0 or p.first_step <= 0 or not p.scales or not p.turns:
        raise ValueError("grid and first_step must be positive, scales and turns non-empty")

    def options_for(scale_set: tuple[float, ...], turn_set: tuple[float, ...]) -> list[LinkOptions]:
        """Candidates of every link for one (Γ, Φ) pair."""
        scales = _ordered(scale_set, 1.0)
        phis = _ordered(turn_set, 0.0)
        # C1 |1 - γ| + C2 |φ| per (γ, φ)
        cost = p.c1 * np.abs(1.0 - scales)[:, None] + p.c2 * np.abs(phis)[None, :]
        out = []
        for i in range(lengths.size):
            if i == 0 and heading is None:
                # θ_k = k Δθ ∈ [-π, π), free of charge; 0 and every multiple of the
                # step are tried, so a track on the Φ lattice can be found exactly.
                ks = np.arange(-np.floor(np.pi / p.first_step), np.ceil(np.pi / p.first_step))
                theta = p.first_step * ks
                theta = theta[(theta >= -np.pi) & (theta < np.pi)]
                theta = theta[np.lexsort((theta, np.abs(theta)))]
                free_cost = np.repeat(p.c1 * np.abs(1.0 - scales)[:, None], theta.size, axis=1)
                out.append(LinkOptions(scales, theta, np.full(theta.size, np.nan), free_cost))
            else:
                out.append(LinkOptions(scales, turns[i] + phis, phis, cost))
        return out

    normal = options_for(p.scales, p.turns)
    wide = options_for(p.wide_scales or p.scales, p.wide_turns or p.turns)
    n = lengths.size
    psi0 = 0.0 if heading is None else float(heading)
    used: list[LinkOptions] = []
    relaxed: list[int] = []
    x0 = start

    def result(
        choices: np.ndarray, score: float, alive: list[int], failed: str | None, spread: float = 0.0
    ) -> TrackFit:
        k = choices.size
        how = np.array(relaxed[:k], dtype=np.int8)
        points, gamma, phi, direction = _replay(x0, psi0, lengths, used, choices)
        return TrackFit(
            points,
            float(score),
            gamma,
            phi,
            direction,
            np.array(alive),
            failed,
            relaxed=how,
            start_shift=float(np.hypot(*(x0 - start))),
            spread=spread,
            cell=cell,
        )

    # Longest move tested: the longest candidate link.
    longest = max(max(p.scales), max(p.wide_scales or p.scales), 1.0)
    cell = p.grid
    if p.cell_per_link > 0 and n:
        # A link shorter than the cell mostly ends in the cell it started from,
        # where only the cheapest track survives: the DP turns greedy. Cells no
        # larger than the typical link keep its alternatives apart.
        cell = min(cell, p.cell_per_link * float(np.median(lengths)))
        cell = max(cell, plan.cell)
    grid = cell_grid(plan, cell, longest * float(lengths.max()) if n else 0.0)
    if not bool(plan.is_free(start)):
        snapped = plan.project(start)
        if p.snap_start <= 0 or float(np.hypot(*(snapped - start))) > p.snap_start:
            return result(np.zeros(0, np.int64), 0.0, [], "start is not in free space")
        x0 = snapped

    xi = x0[None, :]
    psi = np.array([psi0])
    f = np.zeros(1)
    preds: list[np.ndarray] = []
    choices: list[np.ndarray] = []
    alive: list[int] = []
    failed = None
    for i in range(n):
        # Γ and Φ; then the recovery ladder of a dead link, each rung tried only
        # when the one before left no track: Γ_w and Φ_w; walls ignored with
        # the end on free space; pure dead reckoning.
        ladder = [(RELAX_NONE, normal[i], True, True)]
        if p.recover:
            # γ = 1, φ = 0 (any direction for a first link of unknown heading)
            rel = normal[i].rel if heading is None and i == 0 else turns[i : i + 1]
            phi = normal[i].phi if heading is None and i == 0 else np.zeros(1)
            straight = LinkOptions(np.ones(1), rel, phi, np.zeros((1, rel.size)))
            ladder += [
                (RELAX_WIDENED, wide[i], True, True),
                (RELAX_CROSSED, normal[i], True, False),
                (RELAX_DEAD_RECKONED, straight, False, False),
            ]
        for rung in ladder:
            _, opt, free_end, walls = rung
            cells, xi2, psi2, f2, pred, choice = advance(
                grid,
                xi,
                psi,
                f,
                opt.scales * lengths[i],
                opt.rel,
                opt.cost,
                free_end=free_end,
                walls=walls,
            )
            if cells.size:
                break
        alive.append(int(cells.size))
        if cells.size == 0:
            failed = f"no track survives link {i + 1} of {n}"
            break
        used.append(opt)
        relaxed.append(rung[0])
        xi, psi, f = xi2, psi2, f2
        preds.append(pred.astype(np.int32))
        choices.append(choice.astype(np.int32))
        if clock() - t0 > p.time_limit_s and i + 1 < n:
            failed = f"time limit of {p.time_limit_s} s reached after link {i + 1} of {n}"
            break

    # Backward pass: s*_{i-1} = ζ_i(s*_i) from the best last cell (lowest cell on ties).
    j = int(np.argmin(f))
    score = float(f[j])
    # Ends of the other tracks that score within the margin: as good an
    # explanation of the input, so the fit is only as certain as they agree.
    near = f <= score + p.spread_margin
    spread = float(np.hypot(*(xi[near] - xi[j]).T).max())
    k = len(choices)
    path = np.empty(k, dtype=np.int64)
    for i in range(k - 1, -1, -1):
        path[i] = choices[i][j]
        j = int(preds[i][j])
    return result(path, score, alive, failed, spread)
