"""Planning: the a-priori accuracy a layout of transmitters or anchors gives, cell by cell."""

from __future__ import annotations

import io
from typing import Literal

import numpy as np
from sqlalchemy.orm import Session

from app.core.errors import Invalid
from app.engine.accuracy_map import AccuracyMap, floor_accuracy
from app.floors.service import require_floor
from app.geometry.floormap import parse_floor_map
from app.geometry.raster import wall_segments
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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    floor = require_floor(db=db, site_id=site.id, floor_id=floor_id)
    fmap = parse_floor_map(floor.geojson)
    horizontal = np.hypot(result.sigma_x, result.sigma_y)
    ny, nx = result.shape
    extent = (
        result.origin[0],
        result.origin[0] + nx * result.cell,
        result.origin[1],
        result.origin[1] + ny * result.cell,
    )
    width = extent[1] - extent[0]
    height = extent[3] - extent[2]
    fig, ax = plt.subplots(figsize=(8, max(3.0, 8 * height / max(width, 1e-9))), dpi=100)
    finite = horizontal[np.isfinite(horizontal)]
    vmax = float(np.percentile(finite, 95)) if finite.size else 1.0
    image = ax.imshow(
        horizontal, origin="lower", extent=extent, cmap="viridis_r", vmin=0, vmax=vmax
    )
    for x1, y1, x2, y2 in wall_segments(fmap):
        ax.plot([x1, x2], [y1, y2], color="black", linewidth=0.6)
    emitters = fmap.of_kind("transmitter" if tech == "ble" else "anchor")
    if emitters:
        ax.scatter([e.x for e in emitters], [e.y for e in emitters], marker="^", color="red", s=25)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{site.id}/{floor_id}: expected horizontal error ({tech})")
    fig.colorbar(image, ax=ax, label="σ horizontal (m)", shrink=0.8)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()
