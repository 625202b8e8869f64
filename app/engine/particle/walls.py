"""Map constraints of step 2: whether a particle's straight move stays on free cells.

Moves are checked on a flat copy of the floor raster padded with blocked
cells, so sample points need no bounds checks. A move within the clearance
of both its ends is free without tracing; the others are sampled every half
cell at most, ``FloorPlan.segment_free``'s rule applied to each move.
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
    together span it (both ends are looked up anyway); for the others only
    the points outside both reaches are looked up.

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
    """Look up the half-cell points of moves (cells, flat) that neither end vouches for.

    Moves are sorted by how many points they need, most first, so that the
    moves still being traced at step j are a leading slice.
    """
    # k = ⌈|move| / ½⌉ points after the start, h = |move| / k apart
    k = np.maximum(np.ceil(2.0 * length), 1.0).astype(np.float32)
    inv_h = k / np.maximum(length, np.float32(1e-6))
    # the start vouches for j h < reach0, the end for (k - j) h < reach1 and itself
    first = np.maximum(np.ceil(reach0 * inv_h), 1.0)
    last = np.floor(np.minimum(k - reach1 * inv_h, k - 0.5))
    count = np.maximum(last - first + 1.0, 0.0).astype(np.uint16)
    # a radix sort on small integers, most points first
    order = np.argsort(np.iinfo(np.uint16).max - count, kind="stable")
    count = count[order]
    tu, tv = du[order] / k[order], dv[order] / k[order]
    # p = p₀ + j Δp / k from the first point to look up, then one step a time
    su = u0[order] + first[order] * tu
    sv = v0[order] + first[order] * tv
    active = np.searchsorted(-count.astype(np.int32), -np.arange(1, int(count[0]) + 1), "right")
    good = np.ones(count.size, bool)
    for m in active.tolist():
        free = walls.free.take(walls.index(su[:m], sv[:m]), mode="clip")
        np.logical_and(good[:m], free, out=good[:m])
        su[:m] += tu[:m]
        sv[:m] += tv[:m]
    out = np.empty(count.size, bool)
    out[order] = good
    return out
