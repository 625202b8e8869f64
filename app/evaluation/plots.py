"""Estimate-versus-truth plots over a floor plan, shared by the evaluations."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from app.engine.plan import FloorPlan


@contextmanager
def plan_figure(path: Path, plan: FloorPlan, title: str, width_in: float) -> Iterator[Any]:
    """Yield axes with the plan's walkable area drawn grey-on-white; save a PNG on exit.

    The caller draws truth and estimates (metres, the plan's frame) and may
    set limits; the aspect, labels, legend and file are handled here.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xmin, ymin, xmax, ymax = plan.bounds
    height_in = width_in * (ymax - ymin) / max(xmax - xmin, 1e-6) + 0.5
    fig, ax = plt.subplots(figsize=(width_in, height_in))
    ax.imshow(
        plan.free,
        origin="lower",
        extent=(xmin, xmax, ymin, ymax),
        cmap="Greys_r",
        alpha=0.35,
        interpolation="nearest",
    )
    try:
        yield ax
        ax.set_aspect("equal")
        ax.set_title(title)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.legend(loc="best", fontsize=8)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
    finally:
        plt.close(fig)
