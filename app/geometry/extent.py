"""Size checks of an uploaded floor map, before it is rasterised.

A floor's occupancy raster grows with the square of its size: an outline
drawn in kilometres, or in longitude/latitude degrees (a hundredth of a
metre across when read as metres), would make rasterising fail or exhaust
memory. These checks name such a map's mistake instead. They apply to
uploads only: a map already stored keeps loading under whatever limits
were in force when it was accepted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.geometry.floormap import Problem

MIN_EXTENT_M = 1.0
"""An outline narrower than this in both axes is not a floor in metres."""

DEGREES_SPREAD = 100.0
"""A tiny outline this many of its own sizes away from the origin reads as degrees."""


@dataclass(frozen=True)
class ExtentLimits:
    """How large a floor map may be: across (m) and as a raster (cells of ``cell`` m)."""

    max_extent_m: float
    max_raster_cells: int
    cell: float


def _coordinates(geometry: dict[str, Any]) -> np.ndarray:
    """Return every (x, y) of a validated GeoJSON geometry, shape (N, 2)."""
    flat: list[list[float]] = []

    def walk(node: Any) -> None:
        if node and isinstance(node[0], int | float):
            flat.append([float(node[0]), float(node[1])])
        else:
            for child in node:
                walk(child)

    walk(geometry["coordinates"])
    return np.array(flat, dtype=float).reshape(-1, 2)


def _box(xy: np.ndarray) -> tuple[float, float, float, float]:
    """Return (xmin, ymin, xmax, ymax) of points (N, 2)."""
    (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)
    return float(x0), float(y0), float(x1), float(y1)


def _metres(value: float) -> str:
    return f"{value:,.0f} m" if value >= 10 else f"{value:.3g} m"


def _outline_problems(
    index: int, box: tuple[float, float, float, float], limits: ExtentLimits
) -> list[Problem]:
    """Return what is wrong with the outline's size: degrees, too small, too large."""
    x0, y0, x1, y1 = box
    width, height = x1 - x0, y1 - y0
    size = f"{_metres(width)} × {_metres(height)}"
    if max(width, height) < MIN_EXTENT_M:
        geographic = -180 <= x0 and x1 <= 180 and -90 <= y0 and y1 <= 90
        far = math.hypot((x0 + x1) / 2, (y0 + y1) / 2) > DEGREES_SPREAD * max(width, height)
        if geographic and far:
            reason = (
                f"coordinates look like longitude/latitude degrees (x {x0:g} to {x1:g}, y {y0:g} "
                f"to {y1:g}); floor maps are in metres in the floor's local frame (x east, y "
                "north, origin at the plan's bottom-left); place the floor on the globe with the "
                "collection's 'georef' {lon, lat, rotation_deg}"
            )
        else:
            reason = (
                f"outline is only {size} across; floor maps are in metres, and a floor is at "
                f"least {MIN_EXTENT_M:g} m across"
            )
        return [Problem(index, "outline", reason)]
    if max(width, height) > limits.max_extent_m:
        return [
            Problem(
                index,
                "outline",
                f"outline is {size} across, larger than the limit of "
                f"{_metres(limits.max_extent_m)} (LOCUS_FLOOR_MAX_EXTENT_M); floor maps are in "
                "metres",
            )
        ]
    # the raster adds a cell of margin on each side (app/geometry/raster.py)
    cells = (math.ceil(width / limits.cell) + 3) * (math.ceil(height / limits.cell) + 3)
    if cells > limits.max_raster_cells:
        return [
            Problem(
                index,
                "outline",
                f"outline is {size} across: {cells:,} raster cells of {limits.cell:g} m, more "
                f"than the limit of {limits.max_raster_cells:,} (LOCUS_FLOOR_MAX_RASTER_CELLS; a "
                "coarser LOCUS_RASTER_CELL takes larger floors)",
            )
        ]
    return []


def extent_problems(doc: dict[str, Any], limits: ExtentLimits) -> list[Problem]:
    """Return the size problems of a map that ``parse_floor_map`` accepted.

    The outline must be at least a metre and at most ``max_extent_m`` across
    and fit the raster budget; every other feature must keep the map within
    ``max_extent_m`` of the outline (a wall far away would be rasterised
    along its whole length).
    """
    features = doc["features"]
    boxes = [_box(_coordinates(f["geometry"])) for f in features]
    index = next(i for i, f in enumerate(features) if f["properties"]["kind"] == "outline")
    problems = _outline_problems(index, boxes[index], limits)
    if problems:
        return problems
    ox0, oy0, ox1, oy1 = boxes[index]
    for i, (x0, y0, x1, y1) in enumerate(boxes):
        span = max(max(x1, ox1) - min(x0, ox0), max(y1, oy1) - min(y0, oy0))
        if i != index and span > limits.max_extent_m:
            problems.append(
                Problem(
                    i,
                    features[i]["properties"]["kind"],
                    f"lies at x {x0:g} to {x1:g}, y {y0:g} to {y1:g}, making the map "
                    f"{_metres(span)} across with the outline, larger than the limit of "
                    f"{_metres(limits.max_extent_m)} (LOCUS_FLOOR_MAX_EXTENT_M)",
                )
            )
    return problems
