"""Rasterised floor geometry for the filters' hot paths.

The particle filter and the track fitter ask "is this point walkable?" and
"does this move cross a wall?" for thousands of points per update. Exact
polygon tests cost microseconds each; a boolean occupancy raster answers both
with a gather. Walls, barrier edges and the outline are burnt into the raster
with 4-connected (supercover) lines, so no straight move sampled at half a
cell can slip through a wall diagonally between two of its cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


class NoFreeCell(ValueError):
    """The walkable area covers no cell of the raster: nowhere to put a position."""


@dataclass(frozen=True, eq=False)
class FloorPlan:
    """Occupancy raster of one floor in its local metric frame.

    Attributes
    ----------
    origin : ndarray, shape (2,)
        x, y (m) of the lower-left corner of cell (0, 0).
    cell : float
        Cell side (m).
    free : ndarray of bool, shape (ny, nx)
        True where a position may be (row 0 at ``origin[1]``).
    clearance : ndarray of float32, shape (ny, nx)
        Distance (m) from each free cell's centre to the nearest blocked cell;
        0 on blocked cells. A straight move shorter than the clearance at its
        start cannot cross anything.
    nearest : ndarray of int32, shape (2, ny, nx)
        Row and column of the nearest free cell (itself when free).
    """

    origin: np.ndarray
    cell: float
    free: np.ndarray
    clearance: np.ndarray
    nearest: np.ndarray

    @classmethod
    def from_raster(cls, *, origin: np.ndarray, cell: float, free: np.ndarray) -> FloorPlan:
        """Build the derived lookup tables for a free-space raster."""
        free = np.ascontiguousarray(free, dtype=bool)
        if not free.any():
            raise NoFreeCell("floor plan has no free cell")
        clearance = ndimage.distance_transform_edt(free).astype(np.float32) * cell
        # Distance transform of the blocked set gives, for every cell, the
        # index of the closest free cell: projection becomes one gather.
        _, nearest = ndimage.distance_transform_edt(~free, return_indices=True)
        return cls(
            origin=np.asarray(origin, dtype=float),
            cell=float(cell),
            free=free,
            clearance=clearance,
            nearest=nearest.astype(np.int32),
        )

    @property
    def shape(self) -> tuple[int, int]:
        """Raster shape (ny, nx)."""
        return self.free.shape

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """Raster extent (xmin, ymin, xmax, ymax) in metres."""
        ny, nx = self.shape
        x0, y0 = self.origin
        return (x0, y0, x0 + nx * self.cell, y0 + ny * self.cell)

    def cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return row, column and in-raster flag of points ``xy`` (..., 2)."""
        ij = np.floor((np.asarray(xy, dtype=float) - self.origin) / self.cell).astype(np.int64)
        ny, nx = self.shape
        col, row = ij[..., 0], ij[..., 1]
        inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
        return np.clip(row, 0, ny - 1), np.clip(col, 0, nx - 1), inside

    def is_free(self, xy: np.ndarray) -> np.ndarray:
        """Return whether each point (..., 2) lies on a free cell."""
        row, col, inside = self.cell_of(xy)
        return inside & self.free[row, col]

    def segment_free(self, start: np.ndarray, end: np.ndarray) -> np.ndarray:
        """Return whether each straight move ``start → end`` (N, 2) stays free.

        Moves are sampled every half cell, which with supercover-burnt walls
        catches every crossing of a wall. Cost: N × max_length / (cell / 2)
        gathers.
        """
        start = np.asarray(start, dtype=float)
        end = np.asarray(end, dtype=float)
        length = np.linalg.norm(end - start, axis=-1)
        if length.size == 0:
            return np.ones(length.shape, dtype=bool)
        steps = max(1, int(np.ceil(length.max() / (0.5 * self.cell))))
        frac = np.linspace(0.0, 1.0, steps + 1)
        # points[k, n] = start + frac_k (end - start)
        points = start[None] + frac[:, None, None] * (end - start)[None]
        return np.asarray(self.is_free(points).all(axis=0))

    def project(self, xy: np.ndarray) -> np.ndarray:
        """Move each point (..., 2) off blocked cells to the nearest free cell's centre."""
        xy = np.asarray(xy, dtype=float)
        row, col, _ = self.cell_of(xy)
        ok = self.is_free(xy)
        r2 = self.nearest[0][row, col]
        c2 = self.nearest[1][row, col]
        centre = self.origin + (np.stack([c2, r2], axis=-1) + 0.5) * self.cell
        return np.where(ok[..., None], xy, centre)

    def sample_free(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Draw ``n`` points uniformly over the free area, shape (n, 2)."""
        flat = np.flatnonzero(self.free)
        pick = flat[rng.integers(0, flat.size, size=n)]
        row, col = np.divmod(pick, self.shape[1])
        jitter = rng.random((n, 2))
        return self.origin + (np.stack([col, row], axis=-1) + jitter) * self.cell

    def clearance_at(self, xy: np.ndarray) -> np.ndarray:
        """Return the clearance (m) at each point (..., 2); 0 where blocked or outside."""
        row, col, inside = self.cell_of(xy)
        return np.where(inside, self.clearance[row, col], 0.0)


def burn_segments(
    free: np.ndarray, segments: np.ndarray, *, origin: np.ndarray, cell: float
) -> None:
    """Mark the cells every segment (M, 4: x1, y1, x2, y2) passes through as blocked.

    Supercover rasterisation: each segment is sampled at a quarter cell and,
    where two consecutive samples fall in diagonal neighbours, the shared
    side cell is blocked too, so the burnt line is 4-connected.
    """
    if len(segments) == 0:
        return
    ny, nx = free.shape
    seg = np.asarray(segments, dtype=float)
    a, b = seg[:, :2], seg[:, 2:]
    length = np.linalg.norm(b - a, axis=1)
    counts = np.maximum(2, np.ceil(length / (0.25 * cell)).astype(np.int64) + 1)
    owner = np.repeat(np.arange(len(seg)), counts)
    start = np.cumsum(counts) - counts
    k = np.arange(owner.size) - np.repeat(start, counts)
    frac = k / np.repeat(counts - 1, counts)
    points = a[owner] + frac[:, None] * (b - a)[owner]
    ij = np.floor((points - origin) / cell).astype(np.int64)
    col = np.clip(ij[:, 0], 0, nx - 1)
    row = np.clip(ij[:, 1], 0, ny - 1)
    free[row, col] = False
    same_owner = owner[1:] == owner[:-1]
    diagonal = same_owner & (row[1:] != row[:-1]) & (col[1:] != col[:-1])
    free[row[:-1][diagonal], col[1:][diagonal]] = False
