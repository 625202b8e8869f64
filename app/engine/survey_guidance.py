"""Where a site's radio map is thin: the positioning error to expect over each floor.

A build locates every survey scan on maps made without its walk
(``app.engine.crossval``); the error of that held-out fix says how well the
other walks' fingerprints place a receiver standing where the scan was taken.
Smoothing those errors over the floor gives each walkable cell the error a
receiver there should expect, which is what an admin needs to decide where
to survey next:

* each cell's value is the Nadaraya-Watson (kernel-weighted) mean of the
  held-out errors around it, ``ê(x) = Σ wᵢ eᵢ / Σ wᵢ`` with Gaussian weights
  ``wᵢ = exp(-|x - xᵢ|² / 2h²)`` of bandwidth ``h`` (``bandwidth_m``), scans
  beyond ``KERNEL_CUTOFF_SIGMAS · h`` left out;
* a scan whose fix fell on a wrong floor counts as ``wrong_floor_m``, the
  figure the per-scan k-NN's tuning gives the same mistake;
* a cell farther than ``reach_m`` from every held-out scan of its floor has no
  value (NaN): nobody surveyed near it, so nothing is known there; the
  distance to the nearest scan is given beside it, so the unsurveyed part
  can still be drawn by how far it lies from the survey.

Distances are straight lines: a wall between a cell and a scan does not
count. Where a part of the floor was walked by one survey only, its scans were
held out with no other walk nearby, so the held-out errors there are large:
the map says "survey here again" before a user finds out.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from app.engine.crossval import HeldOut
from app.engine.plan import FloorPlan
from app.engine.radiomap import Survey, walkable_cells
from app.engine.scan_knn_cv import WRONG_FLOOR_M

KERNEL_CUTOFF_SIGMAS = 3.0
"""Scans farther than this many bandwidths from a cell are not weighed (weight < 1.2%)."""


@dataclass(frozen=True)
class GuidanceParams:
    """Grid and smoothing of a floor's expected-error map.

    Attributes
    ----------
    cell_m : float
        Grid cell side (m): coarse enough for one survey walk to cover a
        corridor's width, fine enough to tell one room from the next.
    bandwidth_m : float
        Standard deviation h (m) of the Gaussian kernel: about the spacing
        of a walker's WiFi scans (one every 2 to 4 s at walking pace), so a
        cell on a walked line averages a few scans of it.
    reach_m : float
        Cells farther than this (m) from every held-out scan are unsurveyed.
    wrong_floor_m : float
        Error (m) a scan located on a wrong floor counts as.
    high_error_m : float
        Expected error (m) above which a cell is summarised as needing more
        survey.
    """

    cell_m: float = 2.0
    bandwidth_m: float = 3.0
    reach_m: float = 6.0
    wrong_floor_m: float = WRONG_FLOOR_M
    high_error_m: float = 8.0


@dataclass(frozen=True, eq=False)
class GuidanceGrid:
    """One floor's expected error; arrays (ny, nx) with row 0 at ``origin[1]``.

    Attributes
    ----------
    origin : ndarray, shape (2,)
        x, y (m) of the lower-left corner of cell (0, 0).
    walkable : ndarray of bool, shape (ny, nx)
        Cells holding walkable space.
    error_m : ndarray, shape (ny, nx)
        Expected error (m); NaN outside the walkable area and where unsurveyed.
    distance_m : ndarray, shape (ny, nx)
        Distance (m) from the cell centre to the nearest held-out scan; NaN
        outside the walkable area, ∞ on a floor with no held-out scan.
    scans : int
        Held-out scans of the floor the grid was smoothed from.
    params : GuidanceParams
        The grid's cell and smoothing.
    """

    origin: np.ndarray
    walkable: np.ndarray
    error_m: np.ndarray
    distance_m: np.ndarray
    scans: int
    params: GuidanceParams = field(default_factory=GuidanceParams)

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape (ny, nx)."""
        return self.walkable.shape

    @property
    def cell(self) -> float:
        """Grid cell side (m)."""
        return self.params.cell_m

    @property
    def unsurveyed(self) -> np.ndarray:
        """Return the walkable cells without an expected error, shape (ny, nx)."""
        return self.walkable & ~np.isfinite(self.error_m)

    @property
    def high(self) -> np.ndarray:
        """Return the walkable cells whose expected error exceeds ``high_error_m``."""
        return self.walkable & (np.nan_to_num(self.error_m) > self.params.high_error_m)


def scan_errors(held: HeldOut, wrong_floor_m: float) -> np.ndarray:
    """Return each held-out scan's error (m), ``wrong_floor_m`` where its floor was wrong."""
    return np.where(held.floor_ok, held.error_m, wrong_floor_m)


def smoothed_errors(
    points: np.ndarray, scan_xy: np.ndarray, errors: np.ndarray, bandwidth_m: float, reach_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Return the kernel-weighted mean error and the nearest-scan distance at each point.

    Parameters
    ----------
    points : ndarray, shape (P, 2)
        Where to estimate (m).
    scan_xy : ndarray, shape (S, 2)
        Surveyed positions of the held-out scans (m).
    errors : ndarray, shape (S,)
        Their errors (m).
    bandwidth_m, reach_m
        Kernel standard deviation, and the distance beyond which a point has no estimate.

    Returns
    -------
    error : ndarray, shape (P,)
        ``Σ wᵢ eᵢ / Σ wᵢ`` (m); NaN farther than ``reach_m`` from every scan.
    distance : ndarray, shape (P,)
        Distance to the nearest scan (m); ∞ without scans.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    n = points.shape[0]
    if len(scan_xy) == 0:
        return np.full(n, np.nan), np.full(n, np.inf)
    scans = cKDTree(np.asarray(scan_xy, dtype=float))
    distance, _ = scans.query(points)
    cutoff = max(KERNEL_CUTOFF_SIGMAS * bandwidth_m, reach_m)
    pairs = cKDTree(points).sparse_distance_matrix(scans, cutoff, output_type="ndarray")
    # wᵢ = exp(-dᵢ² / 2h²)
    w = np.exp(-0.5 * (pairs["v"] / bandwidth_m) ** 2)
    weight = np.bincount(pairs["i"], weights=w, minlength=n)
    e = np.asarray(errors, dtype=float)[pairs["j"]]
    total = np.bincount(pairs["i"], weights=w * e, minlength=n)
    near = (distance <= reach_m) & (weight > 0)
    # ê = Σ wᵢ eᵢ / Σ wᵢ
    error = np.divide(total, weight, out=np.full(n, np.nan), where=near)
    return error, distance


def floor_guidance(
    plan: FloorPlan,
    scan_xy: np.ndarray,
    errors: np.ndarray,
    params: GuidanceParams = GuidanceParams(),
) -> GuidanceGrid:
    """Return the expected-error grid of one floor from its held-out scans (m).

    The grid is ``walkable_cells`` of the plan at ``params.cell_m``: cells are
    walkable when any free plan cell's centre lies in them.
    """
    origin, walkable = walkable_cells(plan, params.cell_m)
    rows, cols = np.nonzero(walkable)
    centres = origin + (np.stack([cols, rows], axis=1) + 0.5) * params.cell_m
    error, distance = smoothed_errors(centres, scan_xy, errors, params.bandwidth_m, params.reach_m)
    error_grid = np.full(walkable.shape, np.nan)
    distance_grid = np.full(walkable.shape, np.nan)
    error_grid[rows, cols] = error
    distance_grid[rows, cols] = distance
    return GuidanceGrid(origin, walkable, error_grid, distance_grid, int(len(scan_xy)), params)


def site_guidance(
    survey: Survey,
    held: HeldOut,
    plans: Mapping[int, FloorPlan],
    params: GuidanceParams = GuidanceParams(),
) -> dict[int, GuidanceGrid]:
    """Return every floor's expected-error grid from one cross-validation's held-out scans.

    ``held.scan`` are rows of ``survey``; each scan counts on its surveyed
    floor. A floor of ``plans`` with no held-out scan is unsurveyed everywhere.
    """
    errors = scan_errors(held, params.wrong_floor_m)
    floor = survey.scan_floor[held.scan]
    xy = survey.scan_xy[held.scan]
    return {
        f: floor_guidance(plan, xy[floor == f], errors[floor == f], params)
        for f, plan in plans.items()
    }
