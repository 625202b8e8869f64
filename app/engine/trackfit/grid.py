"""The track fitter's cells over the floor plan and its wall test on the plan's raster.

Walls are tested on the ``FloorPlan`` raster: a candidate link ending on a
blocked cell is dropped by one gather; a link shorter than the clearance at
its start (less the raster's cell diagonal) cannot cross anything; only the
remaining links are sampled (``segments_free``, the test of
``FloorPlan.segment_free``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from app.engine.plan import FloorPlan


@dataclass(frozen=True)
class CellGrid:
    """The DP cells over the plan and the wall-test lookups derived from its raster.

    Raster lookups work in padded raster units ``u = (x - origin) / rcell +
    pad``: the raster gets ``pad`` blocked cells on every side, more than the
    longest move, so every candidate end point indexes the arrays without a
    bounds test. ``best``, ``first`` and ``mark`` are per-DP-cell scratch
    arrays of ``advance``, +inf, ``NONE`` and False between calls: resetting
    only the touched cells keeps a link's cost independent of the floor's size.
    They hold ``groups`` copies of the cells: hypotheses fitted together keep
    their tracks apart (group g's cell s is slot g · nx · ny + s).
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


def cell_grid(plan: FloorPlan, cell: float, reach: float, groups: int = 1) -> CellGrid:
    """Lay DP cells of side ``cell`` (m) over the plan for moves up to ``reach`` (m) long.

    The scratch arrays hold ``groups`` hypotheses fitted together.
    """
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
        best=np.full(groups * nx * ny, np.inf),
        first=np.full(groups * nx * ny, NONE, dtype=np.int64),
        mark=np.zeros(groups * nx * ny, dtype=bool),
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
