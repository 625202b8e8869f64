"""A grid of values drawn as a heatmap over a floor's plan (walls, optional markers), as PNG:
the picture the accuracy maps and the analytics heatmaps share."""

from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np

from app.geometry.floormap import FloorMap
from app.geometry.raster import wall_segments


def grid_png(
    fmap: FloorMap,
    values: np.ndarray,
    origin: tuple[float, float],
    cell: float,
    *,
    title: str,
    label: str,
    cmap: str,
    vmax: float,
    markers: Sequence[tuple[float, float]] = (),
    greyed: np.ndarray | None = None,
    greyed_label: str = "",
) -> bytes:
    """Return a PNG of ``values`` (ny, nx), row 0 at ``origin[1]``, NaN left blank, under the
    floor's walls and red triangles at ``markers`` (x, y in m); cells of the boolean
    ``greyed`` (ny, nx) are drawn grey, named ``greyed_label`` in the legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    ny, nx = values.shape
    extent = (origin[0], origin[0] + nx * cell, origin[1], origin[1] + ny * cell)
    width = extent[1] - extent[0]
    height = extent[3] - extent[2]
    fig, ax = plt.subplots(figsize=(8, max(3.0, 8 * height / max(width, 1e-9))), dpi=100)
    image = ax.imshow(values, origin="lower", extent=extent, cmap=cmap, vmin=0, vmax=vmax)
    if greyed is not None and greyed.any():
        grey = np.zeros((ny, nx, 4))
        grey[greyed] = (0.55, 0.58, 0.63, 0.8)
        ax.imshow(grey, origin="lower", extent=extent, interpolation="nearest")
        ax.legend(
            handles=[Patch(color=(0.55, 0.58, 0.63, 0.8), label=greyed_label)],
            loc="upper right",
            fontsize="small",
        )
    for x1, y1, x2, y2 in wall_segments(fmap):
        ax.plot([x1, x2], [y1, y2], color="black", linewidth=0.6)
    if markers:
        ax.scatter([m[0] for m in markers], [m[1] for m in markers], marker="^", color="red", s=25)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    fig.colorbar(image, ax=ax, label=label, shrink=0.8)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()
