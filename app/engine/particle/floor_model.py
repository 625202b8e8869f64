"""What the filters of one floor share, built once per site model, and step 1's scatter."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from app.engine.particle.params import ParticleFilterParams
from app.engine.particle.walls import WallRaster
from app.engine.pathloss import RssiGrid, build_rssi_grid, reliable
from app.engine.plan import FloorPlan
from app.engine.radiomap import RadioMap
from app.engine.site import SiteModel


@dataclass(frozen=True, eq=False)
class FloorModel:
    """What the filters of one floor need, built once per site model.

    Attributes
    ----------
    plan : FloorPlan
        Walkable raster with walls, barriers and outline burnt in.
    walls : WallRaster
        The same raster, padded and flat, for move checks.
    free_cells : ndarray of intp
        Flat indices of the plan's free cells, for uniform scattering.
    grid : RssiGrid
        Expected RSSI of the floor's transmitters.
    local : ndarray of intp, shape (T,)
        Column of ``grid.codes`` of each site transmitter; -1 when on another floor.
    xy, A, B, sigma : ndarray, shape (T, 2) and (T,)
        The site's transmitter positions (m) and path-loss parameters.
    usable : ndarray of bool, shape (T,)
        On this floor and passing the quality filter (step 4).
    """

    plan: FloorPlan
    walls: WallRaster
    free_cells: np.ndarray
    grid: RssiGrid
    local: np.ndarray
    xy: np.ndarray
    A: np.ndarray
    B: np.ndarray
    sigma: np.ndarray
    usable: np.ndarray


def build_floor_models(
    site: SiteModel,
    params: ParticleFilterParams,
    radio_maps: Sequence[RadioMap] = (),
) -> tuple[FloorModel, ...]:
    """Precompute every floor's free-cell list, padded walls and expected-RSSI raster.

    With ``radio_maps`` (transmitter indices of ``site``), a floor's raster holds
    the surveyed RSSI wherever its map has a reference point, and the path-loss
    model's only where the survey never went (``overlay_radio_map``).
    """
    tx = site.transmitters
    n_tx = len(tx)
    ok = reliable(tx.sigma, tx.B, params.quality_threshold)
    maps = {m.floor: m for m in radio_maps}
    models = []
    for f, floor in enumerate(site.floors):
        on = np.flatnonzero(tx.floor == f) if n_tx else np.zeros(0, np.intp)
        local = np.full(n_tx, -1, dtype=np.intp)
        local[on] = np.arange(on.size)
        grid = build_rssi_grid(floor.plan.bounds, tx.xyz[on], tx.A[on], tx.B[on], params.pathloss)
        if f in maps:
            grid = overlay_radio_map(grid, on, maps[f], params.unheard_dbm)
        models.append(
            FloorModel(
                plan=floor.plan,
                walls=WallRaster.from_plan(floor.plan, params.max_move_m),
                free_cells=np.flatnonzero(floor.plan.free),
                grid=grid,
                local=local,
                xy=np.asarray(tx.xyz, dtype=float).reshape(-1, 3)[:, :2],
                A=np.asarray(tx.A, dtype=float),
                B=np.asarray(tx.B, dtype=float),
                sigma=np.asarray(tx.sigma, dtype=float),
                usable=(local >= 0) & ok,
            )
        )
    return tuple(models)


def overlay_radio_map(
    grid: RssiGrid, on: np.ndarray, radio_map: RadioMap, unheard_dbm: float
) -> RssiGrid:
    """Return the raster with the surveyed mean RSSI at the cells of the map's reference points.

    A measured fingerprint beats a fitted model where there is one: walls,
    shelves and the atrium bend the real field away from ``A - B ln r``. A
    reference point where the survey never heard the transmitter gets
    ``unheard_dbm`` (missing signal is evidence too); cells no survey reached
    keep the model's value.

    Parameters
    ----------
    grid : RssiGrid
        The floor's path-loss raster; column k is transmitter ``on[k]``.
    on : ndarray of intp, shape (T,)
        Site transmitter index of each raster row.
    radio_map : RadioMap
        The floor's radio map, its columns in site transmitter indices.
    """
    cols = radio_map.columns(on) if on.size else np.zeros(0, np.int64)
    xy = radio_map.xy
    cells = grid.cell_index(xy[:, 0], xy[:, 1])
    codes = grid.codes.copy()
    for k in np.flatnonzero(cols >= 0):
        mean = radio_map.mean[:, cols[k]].astype(float)
        rssi = np.where(np.isfinite(mean), mean, unheard_dbm)
        # code = round((rssi - floor) / step), clipped to a byte
        q = np.rint((rssi - grid.floor_dbm) / grid.step_db)
        codes[cells, k] = np.clip(q, 0, 255).astype(np.uint8)
    return replace(grid, codes=codes)


def scatter(model: FloorModel, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 1: positions uniform over the free area and uniform directions.

    Parameters
    ----------
    u : ndarray, shape (..., 4) in [0, 1)
        Uniforms: free cell, x and y inside the cell, direction.

    Returns
    -------
    x, y, alpha : ndarray of float32, shape (...)
        Metres, metres, radians in [-π, π).
    """
    plan = model.plan
    nx = plan.shape[1]
    pick = model.free_cells[(u[..., 0] * model.free_cells.size).astype(np.intp)]
    row, col = np.divmod(pick, nx)
    # x = x₀ + (col + u) c, y = y₀ + (row + u) c
    x = plan.origin[0] + (col + u[..., 1]) * plan.cell
    y = plan.origin[1] + (row + u[..., 2]) * plan.cell
    # α = (2u - 1) π
    alpha = (2.0 * u[..., 3] - 1.0) * np.pi
    return x.astype(np.float32), y.astype(np.float32), alpha.astype(np.float32)
