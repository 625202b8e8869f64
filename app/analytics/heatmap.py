"""A floor's heatmap grid: cells of the outline's bounds, device-seconds summed per cell.

Pure numpy; the database sums each cell's seconds, this places them on the grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Grid:
    """Cells ``cell`` metres square from ``origin`` (x0, y0); shape (ny, nx), row 0 at y0."""

    origin: tuple[float, float]
    cell: float
    shape: tuple[int, int]

    @classmethod
    def over(cls, bounds: tuple[float, float, float, float], cell: float) -> Grid:
        """Return the grid covering ``bounds`` (xmin, ymin, xmax, ymax), as accuracy maps do:
        the last row and column may overhang the bounds."""
        xmin, ymin, xmax, ymax = bounds
        nx = max(1, int(np.ceil((xmax - xmin) / cell - 1e-9)))
        ny = max(1, int(np.ceil((ymax - ymin) / cell - 1e-9)))
        return cls((float(xmin), float(ymin)), float(cell), (ny, nx))

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the cell centres' x and y (m), each shape (ny, nx)."""
        ny, nx = self.shape
        gx = self.origin[0] + (np.arange(nx) + 0.5) * self.cell
        gy = self.origin[1] + (np.arange(ny) + 0.5) * self.cell
        X, Y = np.meshgrid(gx, gy)
        return X, Y


def place(grid: Grid, i: np.ndarray, j: np.ndarray, seconds: np.ndarray) -> np.ndarray:
    """Return the (ny, nx) grid of ``seconds`` summed at column ``i``, row ``j``.

    Indices outside the grid are ignored (positions off the plan's bounds).
    """
    ny, nx = grid.shape
    out = np.zeros((ny, nx))
    keep = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
    np.add.at(out, (j[keep], i[keep]), seconds[keep])
    return out


def to_json(grid: Grid, seconds: np.ndarray, inside: np.ndarray) -> dict[str, Any]:
    """Return the API's heatmap document: ``seconds`` (ny, nx), null outside the outline."""
    rounded = np.round(seconds, 3)
    return {
        "origin": [grid.origin[0], grid.origin[1]],
        "cell": grid.cell,
        "shape": list(grid.shape),
        "seconds": [
            [float(v) if ok else None for v, ok in zip(row, mask, strict=True)]
            for row, mask in zip(rounded, inside, strict=True)
        ],
    }
