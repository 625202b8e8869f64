"""Turn a validated floor map into the engine's occupancy raster."""

from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry.base import BaseGeometry

from app.engine.plan import FloorPlan, burn_segments
from app.geometry.floormap import FloorMap


def _segments(geometry: BaseGeometry) -> np.ndarray:
    """Return every straight edge of lines and polygon rings as (M, 4) x1, y1, x2, y2."""
    parts: list[np.ndarray] = []
    for line in shapely.get_parts(
        shapely.boundary(geometry) if geometry.geom_type.endswith("Polygon") else geometry
    ):
        for piece in shapely.get_parts(line):
            xy = shapely.get_coordinates(piece)
            if len(xy) >= 2:
                parts.append(np.hstack([xy[:-1], xy[1:]]))
    return np.vstack(parts) if parts else np.zeros((0, 4))


def wall_segments(fmap: FloorMap) -> np.ndarray:
    """Return everything that cannot be crossed: walls, barrier edges and the outline."""
    geoms = [fmap.outline, *fmap.walls, *fmap.barriers]
    return np.vstack([_segments(g) for g in geoms])


def floor_plan(fmap: FloorMap, *, cell: float) -> FloorPlan:
    """Rasterise the walkable area at ``cell`` metres with uncrossable edges burnt in."""
    xmin, ymin, xmax, ymax = fmap.outline.bounds
    origin = np.array([np.floor(xmin / cell) * cell - cell, np.floor(ymin / cell) * cell - cell])
    nx = int(np.ceil((xmax - origin[0]) / cell)) + 1
    ny = int(np.ceil((ymax - origin[1]) / cell)) + 1
    xs = origin[0] + (np.arange(nx) + 0.5) * cell
    ys = origin[1] + (np.arange(ny) + 0.5) * cell
    gx, gy = np.meshgrid(xs, ys)
    walkable = fmap.walkable
    shapely.prepare(walkable)
    free = shapely.contains_xy(walkable, gx, gy)
    burn_segments(free, wall_segments(fmap), origin=origin, cell=cell)
    return FloorPlan.from_raster(origin=origin, cell=cell, free=free)
