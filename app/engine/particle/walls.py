"""Map constraints of step 2: whether a particle's straight move stays on free cells.

Moves are checked on a flat copy of the floor raster padded with blocked
cells, so sample points need no bounds checks. A move within the clearance
of both its ends is free without tracing; the others are traced from their
start, ``FloorPlan.segment_free``'s rule (points every half cell at most)
applied to each move, each point looked up vouching for the points within
its clearance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.engine.plan import FloorPlan


@dataclass(frozen=True, eq=False)
class WallRaster:
    """A floor's free cells and clearance, flat and padded with blocked cells.

    Attributes
    ----------
    origin : ndarray, shape (2,)
        x, y (m) of the unpadded raster's cell (0, 0) corner.
    inv_cell : float
        1 / cell side (m⁻¹).
    pad : int
        Blocked cells added on every side: at least the longest move.
    stride : int
        Cells per padded row.
    free : ndarray of uint8, shape (rows × stride,)
        1 on free cells.
    clearance : ndarray of float32, same shape
        Clearance in cells (0 on blocked cells).
    """

    origin: np.ndarray
    inv_cell: float
    pad: int
    stride: int
    free: np.ndarray
    clearance: np.ndarray

    @classmethod
    def from_plan(cls, plan: FloorPlan, max_move_m: float) -> WallRaster:
        """Pad a floor plan by ``max_move_m`` plus two cells of blocked cells."""
        pad = int(np.ceil(max_move_m / plan.cell)) + 2
        ny, nx = plan.shape
        free = np.zeros((ny + 2 * pad, nx + 2 * pad), np.uint8)
        free[pad:-pad, pad:-pad] = plan.free
        clearance = np.zeros(free.shape, np.float32)
        clearance[pad:-pad, pad:-pad] = plan.clearance / plan.cell
        return cls(
            origin=plan.origin.copy(),
            inv_cell=1.0 / plan.cell,
            pad=pad,
            stride=nx + 2 * pad,
            free=free.ravel(),
            clearance=clearance.ravel(),
        )

    def cells(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return padded cell coordinates (float32, in cells) of points (m) on or near the plan."""
        inv = np.float32(self.inv_cell)
        # u = x / c - (x₀ / c - pad), so that ⌊u⌋ is the padded column
        u = np.asarray(x, np.float32) * inv - np.float32(self.origin[0] * self.inv_cell - self.pad)
        v = np.asarray(y, np.float32) * inv - np.float32(self.origin[1] * self.inv_cell - self.pad)
        return u, v

    def index(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return the flat padded index of cell coordinates (non-negative by the padding)."""
        # k = ⌊v⌋ · stride + ⌊u⌋
        return v.astype(np.intp) * self.stride + u.astype(np.intp)


def moves_free(
    walls: WallRaster, x0: np.ndarray, y0: np.ndarray, x1: np.ndarray, y1: np.ndarray
) -> np.ndarray:
    """Return whether each straight move (x0, y0) → (x1, y1) stays on free cells.

    ``FloorPlan.segment_free``'s rule applied to each move: its points at
    k + 1 even steps, both ends included, lie on free cells, k the smallest
    count keeping them at most half a cell apart.

    Most of those points need no lookup. A point closer to a free point p
    than reach(p) = clearance(p) - √2 cells cannot be on a blocked cell (p
    and a blocked cell's points lie within √2 / 2 cells of their cell
    centres). So a move is free outright when the reaches of its two ends
    together span it (both ends are looked up anyway); the others are traced
    from the start, each point looked up vouching for those within its own
    reach (``_trace_moves``).

    Parameters
    ----------
    x0, y0, x1, y1 : ndarray, shape (...)
        Start and end (m); starts on free cells, moves no longer than the padding.
    """
    root2 = np.float32(np.sqrt(2.0))
    u0, v0 = walls.cells(x0, y0)
    u1, v1 = walls.cells(x1, y1)
    du, dv = u1 - u0, v1 - v0
    length = np.sqrt(du * du + dv * dv)
    k1 = walls.index(u1, v1)
    end_free = walls.free.take(k1) > 0
    reach0 = walls.clearance.take(walls.index(u0, v0)) - root2
    reach1 = walls.clearance.take(k1) - root2
    # free ⇐ every point lies within the reach of one end
    ok = end_free & (reach0 + reach1 > length)
    trace = np.flatnonzero((end_free & ~ok).ravel())
    if trace.size:
        ok.ravel()[trace] = _trace_moves(
            walls,
            u0.ravel()[trace],
            v0.ravel()[trace],
            du.ravel()[trace],
            dv.ravel()[trace],
            length.ravel()[trace],
            reach0.ravel()[trace],
            reach1.ravel()[trace],
        )
    return ok


def trace_span(
    du: np.ndarray, dv: np.ndarray, length: np.ndarray, reach0: np.ndarray, reach1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return how to trace moves (cells) the ends do not settle.

    That is the step between points (tu, tv), the points per cell of length
    (k / |move|), and the first and last point to look up. A move has
    k = ⌈|move| / ½⌉ points after the start, h = |move| / k apart; the start
    vouches for the points j with j h < reach0, the end for those with
    (k - j) h < reach1 and itself. All float32, as the compiled kernel
    computes them.
    """
    k = np.maximum(np.ceil(np.float32(2.0) * length), np.float32(1.0))
    inv_h = k / np.maximum(length, np.float32(1e-6))
    first = np.maximum(np.ceil(reach0 * inv_h), np.float32(1.0))
    last = np.floor(np.minimum(k - reach1 * inv_h, k - np.float32(0.5)))
    return du / k, dv / k, inv_h, first, last


def _trace_moves(
    walls: WallRaster,
    u0: np.ndarray,
    v0: np.ndarray,
    du: np.ndarray,
    dv: np.ndarray,
    length: np.ndarray,
    reach0: np.ndarray,
    reach1: np.ndarray,
) -> np.ndarray:
    """Look up the points of moves (cells, flat) that neither end vouches for.

    A sphere trace: point j = first, first + 1, … is p₀ + j Δp / k; a point
    on a blocked cell ends its move, one on a free cell vouches for the next
    ⌈reach · k / |move|⌉ - 1 points, which are skipped. In rounds over the
    moves still being traced, each round one point of each: about half the
    lookups of every point outside the ends' reach.
    """
    root2 = np.float32(np.sqrt(2.0))
    tu, tv, inv_h, j, last = trace_span(du, dv, length, reach0, reach1)
    good = np.ones(u0.size, bool)
    active = np.flatnonzero(j <= last)
    while active.size:
        at = j[active]
        u = u0[active] + at * tu[active]
        v = v0[active] + at * tv[active]
        clearance = walls.clearance.take(walls.index(u, v), mode="clip")
        free = clearance > 0
        good[active] = free
        # the next point outside this one's reach: j + max(⌈(c - √2) k / |move|⌉, 1)
        j[active] = at + np.maximum(np.ceil((clearance - root2) * inv_h[active]), np.float32(1.0))
        active = active[free & (j[active] <= last[active])]
    return good
