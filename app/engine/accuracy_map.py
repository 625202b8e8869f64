"""A-priori accuracy of a beacon or anchor layout over a floor, before anyone measures.

Grinyak's (2020) use of ``D = (Hᵀ Q⁻¹ H)⁻¹``: at every cell centre of a grid at
height z, the standard deviations a least-squares fix would have from the
emitters of a floor with ``samples`` readings each, and the condition number
of the linearised problem. Where the 3-D problem is rank deficient (the cell
in the plane of all emitters) the height is taken as known and only σx, σy
are given; where even 2-D is rank deficient every value is NaN. One SVD per
cell, all cells of a chunk in one batched call: no Python loop over cells.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from app.engine.lateration.accuracy import Model, covariance_checks, path_loss_B, whitened_jacobian
from app.engine.site import Emitters, SiteModel

Tech = Literal["ble", "uwb"]


@dataclass(frozen=True)
class AccuracyParams:
    """Defaults for emitters whose table lacks a value, and the work split.

    Attributes
    ----------
    ble_sigma_db : float
        RSSI standard deviation (dB) of a transmitter without ``sigma``: the
        paper's calibrated 25 dB² (σ = 5 dB).
    ble_B : float
        Path-loss slope B (dB per ln m) of a transmitter without ``B``: the
        paper does not print its exponent n; n = 2 (free space, B = 20 / ln 10
        ≈ 8.69) reproduces its figures (0.48 m horizontal at the hall's
        centre with 4 floor beacons, 0.19 m with 17;
        ``tests/engine/test_accuracy_map.py`` checks them).
    uwb_range_std_m : float
        Two-way-ranging standard deviation (m) of an anchor.
    max_range_m : float
        Emitters farther than this from a cell are not heard there (m).
    chunk_cells : int
        Cells per batched SVD (bounds memory to chunk × emitters × 3 floats).
    """

    ble_sigma_db: float = 5.0
    ble_B: float = path_loss_B(2.0)
    uwb_range_std_m: float = 0.1
    max_range_m: float = np.inf
    chunk_cells: int = 4096


@dataclass(frozen=True)
class AccuracyMap:
    """Expected fix accuracy on a grid; arrays (ny, nx) with row 0 at ``origin[1]``.

    ``sigma_x``, ``sigma_y``, ``sigma_z`` (m) and ``cond`` are NaN where the
    position is unobservable; ``sigma_z`` also where only 2-D was observable.
    """

    origin: np.ndarray
    cell: float
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    sigma_z: np.ndarray
    cond: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape (ny, nx)."""
        return self.sigma_x.shape

    def centres(self) -> np.ndarray:
        """Return the cell centres, shape (ny, nx, 2) (m)."""
        ny, nx = self.shape
        gx = self.origin[0] + (np.arange(nx) + 0.5) * self.cell
        gy = self.origin[1] + (np.arange(ny) + 0.5) * self.cell
        return np.stack(np.meshgrid(gx, gy), axis=-1)

    def to_json(self) -> dict[str, Any]:
        """Return the API's accuracy document (NaN and ∞ become null)."""

        def grid(a: np.ndarray) -> list[list[float | None]]:
            rounded = np.round(a, 4)
            return [[float(v) if np.isfinite(v) else None for v in row] for row in rounded]

        return {
            "origin": [float(self.origin[0]), float(self.origin[1])],
            "cell": float(self.cell),
            "shape": list(self.shape),
            "sigma_x": grid(self.sigma_x),
            "sigma_y": grid(self.sigma_y),
            "sigma_z": grid(self.sigma_z),
            "cond": grid(self.cond),
        }


def accuracy_at(
    points: np.ndarray,
    emitters: np.ndarray,
    std: np.ndarray,
    *,
    model: Model,
    B: np.ndarray | None = None,
    samples: int = 1,
    max_range: float = np.inf,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the predicted σ (P, 3) (m), cond (P,) and observable dims (P,) at points.

    Parameters
    ----------
    points : ndarray, shape (P, 3)
        Positions (m).
    emitters : ndarray, shape (K, 3)
        Anchors or transmitters (m).
    std : ndarray, shape (K,)
        Standard deviation of one reading (m or dB).
    model : {"range", "rssi"}
    B : ndarray, shape (K,), optional
        Path-loss slopes for ``rssi``.
    samples : int
        Readings per emitter (M): each mean has std σ/√M.
    max_range : float
        Emitters farther than this (m) are not heard.

    Returns
    -------
    sigma : ndarray, shape (P, 3)
        √diag D; σz NaN where only 2-D is observable, all NaN where nothing is.
    cond : ndarray, shape (P,)
        Condition number of the whitened H of the problem solved (3-D or 2-D).
    dims : ndarray of int, shape (P,)
        3, 2 (height taken as known) or 0 (unobservable).
    """
    points = np.asarray(points, dtype=float)
    emitters = np.asarray(emitters, dtype=float).reshape(-1, 3)
    if emitters.shape[0] == 0:
        nothing = np.full(points.shape[0], np.nan)
        return np.full((points.shape[0], 3), np.nan), nothing, np.zeros(points.shape[0], int)
    dist = np.linalg.norm(points[:, None, :] - emitters[None, :, :], axis=-1)
    # σ_mean = σ / √M, ∞ (not heard) beyond the range
    std_pm = np.where(
        dist <= max_range, np.asarray(std, dtype=float)[None, :] / np.sqrt(samples), np.inf
    )
    cov3, cond, rank3 = covariance_checks(whitened_jacobian(model, points, emitters, std_pm, 3, B))
    sigma = np.sqrt(np.diagonal(cov3, axis1=1, axis2=2)).copy()
    dims = np.where(rank3 == 3, 3, 0)
    flat = np.flatnonzero(rank3 < 3)
    if flat.size:
        cov2, cond2, rank2 = covariance_checks(
            whitened_jacobian(model, points[flat], emitters, std_pm[flat], 2, B)
        )
        ok2 = rank2 == 2
        sigma[flat, :2] = np.where(
            ok2[:, None], np.sqrt(np.diagonal(cov2, axis1=1, axis2=2)), np.nan
        )
        sigma[flat, 2] = np.nan
        cond[flat] = np.where(ok2, cond2, np.nan)
        dims[flat] = np.where(ok2, 2, 0)
    return sigma, cond, dims


def accuracy_grid(
    bounds: tuple[float, float, float, float],
    cell: float,
    z: float,
    emitters: np.ndarray,
    std: np.ndarray,
    *,
    model: Model,
    B: np.ndarray | None = None,
    samples: int = 1,
    params: AccuracyParams = AccuracyParams(),
) -> AccuracyMap:
    """Return the accuracy map of ``emitters`` over ``bounds`` (xmin, ymin, xmax, ymax) at height z.

    Cells are ``cell`` metres square from (xmin, ymin); the last row and column
    may overhang the bounds. See :func:`accuracy_at` for the other arguments.
    """
    xmin, ymin, xmax, ymax = bounds
    nx = max(1, int(np.ceil((xmax - xmin) / cell - 1e-9)))
    ny = max(1, int(np.ceil((ymax - ymin) / cell - 1e-9)))
    gx = xmin + (np.arange(nx) + 0.5) * cell
    gy = ymin + (np.arange(ny) + 0.5) * cell
    X, Y = np.meshgrid(gx, gy)
    points = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z)])
    sigma = np.empty((points.shape[0], 3))
    cond = np.empty(points.shape[0])
    step = max(1, params.chunk_cells)
    for a in range(0, points.shape[0], step):
        sigma[a : a + step], cond[a : a + step], _ = accuracy_at(
            points[a : a + step],
            emitters,
            std,
            model=model,
            B=B,
            samples=samples,
            max_range=params.max_range_m,
        )
    return AccuracyMap(
        origin=np.array([xmin, ymin], dtype=float),
        cell=float(cell),
        sigma_x=sigma[:, 0].reshape(ny, nx),
        sigma_y=sigma[:, 1].reshape(ny, nx),
        sigma_z=sigma[:, 2].reshape(ny, nx),
        cond=cond.reshape(ny, nx),
    )


def floor_accuracy(
    site: SiteModel,
    floor: int,
    tech: Tech,
    *,
    z: float = 1.0,
    cell: float = 0.5,
    samples: int = 50,
    params: AccuracyParams = AccuracyParams(),
) -> AccuracyMap:
    """Return the accuracy map of one floor's transmitters (``ble``) or anchors (``uwb``).

    The grid covers the floor plan's raster; transmitters without ``sigma``
    or ``B`` get the defaults of ``params``.
    """
    table: Emitters = site.transmitters if tech == "ble" else site.anchors
    on_floor = np.asarray(table.floor) == floor
    xyz = np.asarray(table.xyz, dtype=float)[on_floor]
    if tech == "ble":
        sigma = np.asarray(table.sigma, dtype=float)[on_floor]
        slope = np.asarray(table.B, dtype=float)[on_floor]
        std = np.where(np.isfinite(sigma) & (sigma > 0), sigma, params.ble_sigma_db)
        B = np.where(np.isfinite(slope) & (slope > 0), slope, params.ble_B)
        model: Model = "rssi"
    else:
        std = np.full(xyz.shape[0], params.uwb_range_std_m)
        B = None
        model = "range"
    return accuracy_grid(
        site.floors[floor].plan.bounds,
        cell,
        z,
        xyz,
        std,
        model=model,
        B=B,
        samples=samples,
        params=params,
    )
