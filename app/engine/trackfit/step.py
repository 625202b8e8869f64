"""One link of the track fitter's dynamic programme: extend every track, keep the best per cell.

Voronov et al.'s programme keeps, for every link i and cell s, only the best track of the first
i links ending in s. ``advance`` adds link i to every surviving track with
each candidate length and turn, drops the candidates that end on or cross a
wall, and keeps the least-score one per destination cell.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from app.engine.trackfit.grid import NONE, CellGrid, segments_free


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
    end_cost: Callable[[np.ndarray], np.ndarray] | None = None,
    group: np.ndarray | None = None,
    link_scale: np.ndarray | None = None,
    link_turn: np.ndarray | None = None,
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
    end_cost : callable, optional
        Score added to each candidate from its end point (m), shape (M, 2) →
        (M,): absolute evidence about where the link ends (an anchor).
    group : ndarray of int, shape (K,), optional
        Hypothesis of each track (default all 0): tracks of different groups
        never compete for a cell (``cells`` are then ``group · nx · ny + s``).
    link_scale : ndarray, shape (K,), optional
        Per-track factor on ``lengths`` (the hypothesis' walker scale).
    link_turn : ndarray, shape (K,), optional
        Per-track angle added to ``rel`` (the hypothesis' turn of this link).

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
    # θ = ψ (+ turn of the track's hypothesis) + rel
    ang = psi[:, None] + rel[None, :]
    if link_turn is not None:
        ang += link_turn[:, None]
    cos, sin = np.cos(ang), np.sin(ang)
    # u₀ = (ξ - origin) / cell + pad, the start in padded raster units
    u0 = (xi - grid.origin) / grid.rcell + grid.pad
    # γ l (× the hypothesis' scale) in raster units, (1 or K, G)
    step = lengths[None, :] / grid.rcell
    if link_scale is not None:
        step = link_scale[:, None] * step
    # v = ξ + γ l (cos θ, sin θ), candidates laid out (K, G, A)
    ux = step[:, :, None] * cos[:, None, :]
    ux += u0[:, 0, None, None]
    uy = step[:, :, None] * sin[:, None, :]
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

    # f_i = f_{i-1}(σ) + C1 |1 - γ| + C2 |φ| (+ the anchor's cost at v)
    score = f[k] + cost[g, a]
    if end_cost is not None:
        score += end_cost(grid.origin + grid.rcell * (np.column_stack([ux, uy]) - grid.pad))
    # DP cell of v: ⌊(u - pad) rcell / cell⌋
    ratio = grid.rcell / grid.cell
    dest = ((uy - grid.pad) * ratio).astype(np.int64) * grid.nx
    dest += ((ux - grid.pad) * ratio).astype(np.int64)
    if group is not None:
        dest += group[k].astype(np.int64) * (grid.nx * grid.ny)

    # Two free discs, radius safe(ξ) around the start and safe(v) around the
    # end, cover the move when γ l < safe(ξ) + max(safe(v), 0): no sampling.
    c0 = u0.astype(np.int64)
    safe0 = grid.safe[c0[:, 1] * nxp + c0[:, 0]]
    move = step[k if link_scale is not None else 0, g] * grid.rcell
    needs = move >= safe0[k] + grid.safe_end[cell]
    if not walls:
        needs[:] = False

    def clear(pos: np.ndarray) -> np.ndarray:
        """Return whether the moves of the candidates at positions ``pos`` miss every wall."""
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
