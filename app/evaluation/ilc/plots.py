"""Each method's estimates on one walk drawn against the truth over the walk's floor plan."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.datasets.ilc import Walk
from app.engine.plan import FloorPlan
from app.engine.samples import Estimate
from app.evaluation.ilc.recordings import SiteRecordings
from app.evaluation.plots import plan_figure

METHOD_COLOURS = {
    "wknn": "tab:orange",
    "hmm": "tab:green",
    "pf": "tab:blue",
    "pf-radiomap": "tab:red",
    "hmm + fixed-lag": "tab:purple",
    "hmm + full smoothing": "tab:cyan",
    "+ HMM tracking (live)": "tab:green",
    "+ fixed-lag smoothing": "tab:purple",
    "+ full smoothing": "tab:orange",
}
"""Line colour of each method in the walk plots."""


def plot_walk(
    path: Path,
    site: SiteRecordings,
    walk: Walk,
    results: dict[str, list[Estimate]],
) -> None:
    """Save estimate vs truth over the walk's floor plan as a PNG.

    Estimates on a wrong floor are left out and counted in the legend.
    """
    f = site.floor_index(walk)
    plot_on_plan(path, site.plans[f], f, walk, results)


def plot_on_plan(
    path: Path, plan: FloorPlan, f: int, walk: Walk, results: dict[str, list[Estimate]]
) -> None:
    """Save estimate vs truth over ``plan`` (floor index ``f`` of the estimates) as a PNG."""
    wp = walk.waypoints
    title = f"site1 {walk.floor} walk {walk.walk_id}"
    with plan_figure(path, plan, title, width_in=10.0) as ax:
        ax.plot(wp[:, 1], wp[:, 2], "k.-", lw=2, ms=6, label="waypoints (truth)")
        for name, estimates in results.items():
            on = [e for e in estimates if e.floor == f]
            off = len(estimates) - len(on)
            if on:
                xy = np.array([[e.x, e.y] for e in on])
                ax.plot(
                    xy[:, 0],
                    xy[:, 1],
                    ".-",
                    color=METHOD_COLOURS.get(name),
                    lw=0.8,
                    ms=3,
                    alpha=0.8,
                    label=f"{name} ({off} of {len(estimates)} on a wrong floor)",
                )
        pad = 15.0
        ax.set_xlim(wp[:, 1].min() - pad, wp[:, 1].max() + pad)
        ax.set_ylim(wp[:, 2].min() - pad, wp[:, 2].max() + pad)
