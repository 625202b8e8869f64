"""Planning: the a-priori accuracy a layout of transmitters or anchors gives, cell by cell."""

from __future__ import annotations

from typing import Literal

import numpy as np
from sqlalchemy.orm import Session

from app.core.errors import Invalid
from app.engine.accuracy_map import AccuracyMap, floor_accuracy
from app.floors.render import grid_png
from app.floors.service import require_floor
from app.geometry.floormap import parse_floor_map
from app.sites.assembly import assemble_site
from app.sites.models import Site


def accuracy_map(
    *,
    db: Session,
    site: Site,
    floor_id: str,
    tech: Literal["ble", "uwb"],
    z: float,
    cell: float,
    samples: int,
    raster_cell: float,
    max_cells: int,
) -> AccuracyMap:
    """Compute the floor's accuracy map; NotFound for an unknown floor, Invalid when the grid
    would be too large."""
    require_floor(db=db, site_id=site.id, floor_id=floor_id)
    loaded = assemble_site(db=db, site=site, raster_cell=raster_cell)
    index = loaded.floor_index[floor_id]
    xmin, ymin, xmax, ymax = loaded.model.floors[index].plan.bounds
    cells = np.ceil((xmax - xmin) / cell) * np.ceil((ymax - ymin) / cell)
    if cells > max_cells:
        raise Invalid(f"{int(cells)} cells at {cell} m; at most {max_cells}: use a larger cell")
    return floor_accuracy(loaded.model, index, tech, z=z, cell=cell, samples=samples)


def render_png(*, db: Session, site: Site, floor_id: str, result: AccuracyMap, tech: str) -> bytes:
    """Draw the horizontal accuracy as a heatmap over the floor plan."""
    floor = require_floor(db=db, site_id=site.id, floor_id=floor_id)
    fmap = parse_floor_map(floor.geojson)
    horizontal = np.hypot(result.sigma_x, result.sigma_y)
    finite = horizontal[np.isfinite(horizontal)]
    emitters = fmap.of_kind("transmitter" if tech == "ble" else "anchor")
    return grid_png(
        fmap,
        horizontal,
        (float(result.origin[0]), float(result.origin[1])),
        result.cell,
        title=f"{site.id}/{floor_id}: expected horizontal error ({tech})",
        label="σ horizontal (m)",
        cmap="viridis_r",
        vmax=float(np.percentile(finite, 95)) if finite.size else 1.0,
        markers=[(e.x, e.y) for e in emitters],
    )
