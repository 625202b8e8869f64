"""Particle filter of Eurasian patent 047000 (steps 1–11), batched over many filters.

Each floor a device may be on has its own filter: N particles (x, y, w, α)
with α the particle's walking direction (radians clockwise from +y). One
update, per the patent:

1.  scatter uniformly over the floor's free area when never sampled or when
    the floor had no radio for T_r;
2.  move by the window's steps (or, without an inertial stream, by a random
    walk with a speed prior); a particle whose move would cross a wall or
    barrier or leave the outline stays put and gets a random α; a positional
    measurement pulls particles towards it. The steps of one window (one or
    two at walking cadence, a nearly straight metre or so) are summed into
    one move per particle and checked against the plan once;
3.  rescatter when fewer than N_a particles are alive (w > ε);
4.  drop readings of transmitters with σ / B > S_q;
5.  update weights at most every T_u;
6.  mutation and centre sampling need N_emin visible transmitters;
7.  rescatter N_m random particles;
8.  the sampling centre is the heard transmitter nearest by the inverse path loss;
9.  put N_c random particles around it, Gaussian with variance d_ce;
10. multiply weights by the Gaussian likelihood of the readings, normalise;
11. when Σ w² > 1 / N_r resample N particles from the weights' CDF (at N
    stratified keys, ``resample_indices``), w = 1/N.

Batching: filters of many devices are rows of stacked (D, N) arrays in a
:class:`ParticleBank`; :func:`update_filters` runs one numpy call per
operation for all due filters of a floor. The likelihood is a gather from
the floor's precomputed :class:`~app.engine.pathloss.RssiGrid`.

Randomness: every filter input carries its device's generator, and each
device draws its own blocks in a fixed order (its floors in index order,
then per phase), so a device's particles never depend on which other
devices share its batch. Motion noise is uniform with the configured
standard deviation (numpy's Gaussian draws cost about four uniform ones, and
the sum over windows is Gaussian anyway); the centre sampling of step 9 is
Gaussian as the patent says.

Walls: moves are checked on a flat copy of the floor raster padded with
blocked cells, so sample points need no bounds checks. A move within the
clearance of both its ends is free without tracing; the others are sampled
every half cell at most, ``FloorPlan.segment_free``'s rule applied to each
move.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from app.engine.pathloss import (
    PathLossParams,
    RssiGrid,
    build_rssi_grid,
    grid_log_likelihood,
    range_from_rssi,
    reliable,
)
from app.engine.plan import FloorPlan
from app.engine.radiomap import RadioMap
from app.engine.site import SiteModel

NEVER = np.iinfo(np.int64).min // 2
"""Time (ms) standing for "never"; halved so that differences cannot overflow."""


@dataclass(frozen=True)
class ParticleFilterParams:
    """Constants of the particle filter; the patent's values are the defaults.

    Attributes
    ----------
    n_particles : int
        N, particles per floor filter.
    dead_weight : float
        ε: a particle with w ≤ ε is dead.
    rescatter_after_ms : int
        T_r: scatter anew when the floor has had no radio for this long.
    min_alive : int
        N_a: fewer live particles than this forces a rescatter.
    quality_threshold : float
        S_q: transmitters with σ / B above it are ignored.
    update_interval_ms : int
        T_u: shortest interval between two weight updates.
    min_transmitters : int
        N_emin: visible transmitters needed for mutation and centre sampling.
    n_mutate : int
        N_m: particles rescattered at every weight update.
    n_centre : int
        N_c: particles placed around the sampling centre.
    centre_variance_m2 : float
        d_ce: the patent calls it the dispersion (variance) of the centre
        sampling, so the standard deviation is √d_ce ≈ 2.24 m.
    resample_n : float
        N_r: resample when Σ w² > 1 / N_r, i.e. when the effective sample size
        1 / Σ w² falls below N_r.
    step_length_std_m : float
        Standard deviation (m) of a step's length per particle: σ_d of the
        dead-reckoning patent (seed 002).
    heading_std_deg : float
        Standard deviation (deg) of a step's heading per particle: the
        dead-reckoning heading error measured on ILC site1 (``PdrParams``).
    walk_speed_mps : float
        Random-walk motion without an inertial stream: the speed of each
        particle is Rayleigh with this scale σ_v (m/s), i.e. its velocity
        components are N(0, σ_v²) (pedestrians: mean speed σ_v √(π/2) ≈ 1.25 m/s).
    walk_turn_std_deg : float
        Random-walk motion: standard deviation (deg) of a particle's change of
        direction per √s; particles keep their direction between windows, so
        the cloud follows straight motion, and wall hits turn them.
    max_move_m : float
        Longest move (m) of a particle in one update; longer moves (a random
        walk after a gap) are shortened to it. Sets the raster padding.
    pathloss : PathLossParams
        Path-loss constants and the expected-RSSI raster.
    unheard_dbm : float
        RSSI (dBm) the raster takes at a radio map's reference point whose
        survey scans never heard the transmitter: below phones' sensitivity.
    chunk : int
        Filters per numpy call: 64 amortise numpy's per-call cost over
        64 × N particles (measured against 16, 32 and 128 with ``bench.engine``).
    """

    n_particles: int = 1000
    dead_weight: float = 1e-8
    rescatter_after_ms: int = 45_000
    min_alive: int = 100
    quality_threshold: float = 1.5
    update_interval_ms: int = 1000
    min_transmitters: int = 3
    n_mutate: int = 50
    n_centre: int = 10
    centre_variance_m2: float = 5.0
    resample_n: float = 600.0
    step_length_std_m: float = 0.1
    heading_std_deg: float = 15.0
    walk_speed_mps: float = 1.0
    walk_turn_std_deg: float = 30.0
    max_move_m: float = 10.0
    pathloss: PathLossParams = field(default_factory=PathLossParams)
    unheard_dbm: float = -100.0
    chunk: int = 64


@dataclass(frozen=True, eq=False)
class WallRaster:
    """A floor's free cells and clearance, flat and padded with blocked cells.

    Attributes
    ----------
    origin : ndarray, shape (2,)
        x, y (m) of the unpadded raster's cell (0, 0) corner.
    inv_cell : float
        1 / cell side (m⁻¹).
    pad : int
        Blocked cells added on every side: at least the longest move.
    stride : int
        Cells per padded row.
    free : ndarray of uint8, shape (rows × stride,)
        1 on free cells.
    clearance : ndarray of float32, same shape
        Clearance in cells (0 on blocked cells).
    """

    origin: np.ndarray
    inv_cell: float
    pad: int
    stride: int
    free: np.ndarray
    clearance: np.ndarray

    @classmethod
    def from_plan(cls, plan: FloorPlan, max_move_m: float) -> WallRaster:
        """Pad a floor plan by ``max_move_m`` plus two cells of blocked cells."""
        pad = int(np.ceil(max_move_m / plan.cell)) + 2
        ny, nx = plan.shape
        free = np.zeros((ny + 2 * pad, nx + 2 * pad), np.uint8)
        free[pad:-pad, pad:-pad] = plan.free
        clearance = np.zeros(free.shape, np.float32)
        clearance[pad:-pad, pad:-pad] = plan.clearance / plan.cell
        return cls(
            origin=plan.origin.copy(),
            inv_cell=1.0 / plan.cell,
            pad=pad,
            stride=nx + 2 * pad,
            free=free.ravel(),
            clearance=clearance.ravel(),
        )

    def cells(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return padded cell coordinates (float32, in cells) of points (m) on or near the plan."""
        inv = np.float32(self.inv_cell)
        # u = x / c - (x₀ / c - pad), so that ⌊u⌋ is the padded column
        u = np.asarray(x, np.float32) * inv - np.float32(self.origin[0] * self.inv_cell - self.pad)
        v = np.asarray(y, np.float32) * inv - np.float32(self.origin[1] * self.inv_cell - self.pad)
        return u, v

    def index(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return the flat padded index of cell coordinates (non-negative by the padding)."""
        # k = ⌊v⌋ · stride + ⌊u⌋
        return v.astype(np.intp) * self.stride + u.astype(np.intp)


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


# --- pure steps on stacked filters -------------------------------------------------


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


def moves_free(
    walls: WallRaster, x0: np.ndarray, y0: np.ndarray, x1: np.ndarray, y1: np.ndarray
) -> np.ndarray:
    """Return whether each straight move (x0, y0) → (x1, y1) stays on free cells.

    ``FloorPlan.segment_free``'s rule applied to each move: its points at
    k + 1 even steps, both ends included, lie on free cells, k the smallest
    count keeping them at most half a cell apart.

    Most of those points need no lookup. A point closer to a free point p
    than reach(p) = clearance(p) - √2 cells cannot be on a blocked cell (p
    and a blocked cell's points lie within √2 / 2 cells of their cell
    centres). So a move is free outright when the reaches of its two ends
    together span it (both ends are looked up anyway); for the others only
    the points outside both reaches are looked up.

    Parameters
    ----------
    x0, y0, x1, y1 : ndarray, shape (...)
        Start and end (m); starts on free cells, moves no longer than the padding.
    """
    root2 = np.float32(np.sqrt(2.0))
    u0, v0 = walls.cells(x0, y0)
    u1, v1 = walls.cells(x1, y1)
    du, dv = u1 - u0, v1 - v0
    length = np.sqrt(du * du + dv * dv)
    k1 = walls.index(u1, v1)
    end_free = walls.free.take(k1) > 0
    reach0 = walls.clearance.take(walls.index(u0, v0)) - root2
    reach1 = walls.clearance.take(k1) - root2
    # free ⇐ every point lies within the reach of one end
    ok = end_free & (reach0 + reach1 > length)
    trace = np.flatnonzero((end_free & ~ok).ravel())
    if trace.size:
        ok.ravel()[trace] = _trace_moves(
            walls,
            u0.ravel()[trace],
            v0.ravel()[trace],
            du.ravel()[trace],
            dv.ravel()[trace],
            length.ravel()[trace],
            reach0.ravel()[trace],
            reach1.ravel()[trace],
        )
    return ok


def _trace_moves(
    walls: WallRaster,
    u0: np.ndarray,
    v0: np.ndarray,
    du: np.ndarray,
    dv: np.ndarray,
    length: np.ndarray,
    reach0: np.ndarray,
    reach1: np.ndarray,
) -> np.ndarray:
    """Look up the half-cell points of moves (cells, flat) that neither end vouches for.

    Moves are sorted by how many points they need, most first, so that the
    moves still being traced at step j are a leading slice.
    """
    # k = ⌈|move| / ½⌉ points after the start, h = |move| / k apart
    k = np.maximum(np.ceil(2.0 * length), 1.0).astype(np.float32)
    inv_h = k / np.maximum(length, np.float32(1e-6))
    # the start vouches for j h < reach0, the end for (k - j) h < reach1 and itself
    first = np.maximum(np.ceil(reach0 * inv_h), 1.0)
    last = np.floor(np.minimum(k - reach1 * inv_h, k - 0.5))
    count = np.maximum(last - first + 1.0, 0.0).astype(np.uint16)
    # a radix sort on small integers, most points first
    order = np.argsort(np.iinfo(np.uint16).max - count, kind="stable")
    count = count[order]
    tu, tv = du[order] / k[order], dv[order] / k[order]
    # p = p₀ + j Δp / k from the first point to look up, then one step a time
    su = u0[order] + first[order] * tu
    sv = v0[order] + first[order] * tv
    active = np.searchsorted(-count.astype(np.int32), -np.arange(1, int(count[0]) + 1), "right")
    good = np.ones(count.size, bool)
    for m in active.tolist():
        free = walls.free.take(walls.index(su[:m], sv[:m]), mode="clip")
        np.logical_and(good[:m], free, out=good[:m])
        su[:m] += tu[:m]
        sv[:m] += tv[:m]
    out = np.empty(count.size, bool)
    out[order] = good
    return out


def window_displacement(
    length: np.ndarray,
    heading: np.ndarray,
    alpha: np.ndarray,
    noise: np.ndarray,
    params: ParticleFilterParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2: each particle's move over one window's steps, and its new direction.

    Each particle draws one length error ε_L and one heading error ε_θ per
    window, shared by the window's steps:
    Δ = Σ_j (L_j + ε_L) (sin(θ_j + ε_θ), cos(θ_j + ε_θ)), the new α = θ_last + ε_θ.
    Rows whose steps lack a heading (no heading source) walk along α instead:
    Δ = (Σ L_j + k ε_L) (sin(α + ε_θ), cos(α + ε_θ)).

    Parameters
    ----------
    length : ndarray, shape (D, K)
        Step lengths (m), 0 for padding.
    heading : ndarray, shape (D, K)
        Step headings (rad clockwise from +y), NaN unknown; padding repeats
        the last real step's heading.
    alpha : ndarray of float32, shape (D, N)
        Current particle directions (rad).
    noise : ndarray of float32, shape (2, D, N)
        Uniforms in [0, 1) for the length and heading errors.

    Returns
    -------
    dx, dy, direction : ndarray of float32, shape (D, N)
    """
    root3 = np.float32(np.sqrt(3.0))
    # uniform on [-√3 σ, √3 σ) has standard deviation σ
    e_len = (2.0 * noise[0] - 1.0) * (root3 * np.float32(params.step_length_std_m))
    e_dir = (2.0 * noise[1] - 1.0) * (root3 * np.float32(np.radians(params.heading_std_deg)))
    real = length > 0
    known = ~np.isnan(heading).any(axis=1)
    dx = np.empty(alpha.shape, np.float32)
    dy = np.empty(alpha.shape, np.float32)
    direction = np.empty(alpha.shape, np.float32)
    if known.any():
        rows = np.flatnonzero(known)
        h = heading[rows]
        sin_h, cos_h = np.sin(h) * real[rows], np.cos(h) * real[rows]
        # V = Σ L_j u_j, U = Σ u_j, u_j = (sin θ_j, cos θ_j)
        vx = np.sum(length[rows] * sin_h, axis=1, keepdims=True).astype(np.float32)
        vy = np.sum(length[rows] * cos_h, axis=1, keepdims=True).astype(np.float32)
        ux = np.sum(sin_h, axis=1, keepdims=True).astype(np.float32)
        uy = np.sum(cos_h, axis=1, keepdims=True).astype(np.float32)
        el, ed = e_len[rows], e_dir[rows]
        s, c = np.sin(ed), np.cos(ed)
        # (a, b) = V + ε_L U, rotated clockwise by ε_θ
        a = vx + el * ux
        b = vy + el * uy
        dx[rows] = a * c + b * s
        dy[rows] = b * c - a * s
        direction[rows] = h[:, -1:].astype(np.float32) + ed
    if not known.all():
        rows = np.flatnonzero(~known)
        k = real[rows].sum(axis=1, keepdims=True).astype(np.float32)
        total = length[rows].sum(axis=1, keepdims=True).astype(np.float32)
        free_dir = alpha[rows] + e_dir[rows]
        # along α: ℓ = Σ L_j + k ε_L
        ell = np.maximum(total + k * e_len[rows], 0.0)
        dx[rows] = ell * np.sin(free_dir)
        dy[rows] = ell * np.cos(free_dir)
        direction[rows] = free_dir
    return dx, dy, direction


def walk_displacement(
    dt_s: np.ndarray, alpha: np.ndarray, noise: np.ndarray, params: ParticleFilterParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2 without an inertial stream: a correlated random walk with a speed prior.

    The speed prior is Rayleigh with scale σ_v, the speed of a velocity whose
    components are independent N(0, σ_v²); it is drawn by inverting its CDF.

    Parameters
    ----------
    dt_s : ndarray, shape (D, 1)
        Time since the previous update (s).
    alpha : ndarray of float32, shape (D, N)
        Current particle directions (rad).
    noise : ndarray of float32, shape (2, D, N)
        Uniforms in [0, 1) for the speed and the turn.

    Returns
    -------
    dx, dy, direction : ndarray of float32, shape (D, N)
    """
    dt = np.asarray(dt_s, dtype=np.float32)
    root3 = np.float32(np.sqrt(3.0))
    turn_sd = np.float32(np.radians(params.walk_turn_std_deg))
    # turn ~ uniform with σ = σ_turn √Δt
    direction = alpha + (2.0 * noise[1] - 1.0) * (root3 * turn_sd * np.sqrt(dt))
    # |v| = σ_v √(-2 ln(1 - u)), Δ = |v| Δt (sin α, cos α); u < 1 even after rounding to float32
    u = np.minimum(noise[0], np.float32(1.0 - 2.0**-24))
    speed = np.float32(params.walk_speed_mps) * np.sqrt(-2.0 * np.log1p(-u))
    step = speed * dt
    return step * np.sin(direction), step * np.cos(direction), direction


def alive_count(w: np.ndarray, eps: float) -> np.ndarray:
    """Step 3: number of particles with weight above ε, per filter (D,)."""
    return np.count_nonzero(w > eps, axis=-1)


def sampling_centre(
    rssi: np.ndarray, A: np.ndarray, B: np.ndarray, valid: np.ndarray
) -> np.ndarray:
    """Step 8: index of the heard transmitter nearest by the inverse path loss.

    Parameters
    ----------
    rssi, A, B : ndarray, shape (D, M)
        Mean reading (dBm) and path-loss parameters of each heard transmitter.
    valid : ndarray of bool, shape (D, M)
        False for padding and filtered transmitters.

    Returns
    -------
    ndarray of intp, shape (D,)
        Column of the nearest transmitter (0 for rows without any).
    """
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        r = range_from_rssi(rssi, A, B)
    return np.argmin(np.where(valid, r, np.inf), axis=-1)


def reweight(w: np.ndarray, ll: np.ndarray) -> np.ndarray:
    """Step 10: multiply weights by likelihoods exp(ll) and normalise each row.

    Parameters
    ----------
    w : ndarray, shape (D, N)
        Current weights, rows summing to 1.
    ll : ndarray, shape (D, N)
        Log-likelihood of each particle, up to a per-row constant.

    Returns
    -------
    ndarray of float64, shape (D, N)
        If every product underflows, the likelihood alone, normalised.
    """
    ll = ll - ll.max(axis=-1, keepdims=True)
    lik = np.exp(ll, dtype=np.float64)
    # w_i ← w_i p_i / Σ_j w_j p_j
    out = w * lik
    total = out.sum(axis=-1, keepdims=True)
    lost = total[:, 0] <= 1e-300
    if lost.any():
        out[lost] = lik[lost]
        total[lost] = lik[lost].sum(axis=-1, keepdims=True)
    return out / total


def needs_resampling(w: np.ndarray, resample_n: float) -> np.ndarray:
    """Step 11's criterion: Σ w² > 1 / N_r, per filter (D,)."""
    # Σ_i w_i² > 1 / N_r
    return np.einsum("dn,dn->d", w, w) > 1.0 / resample_n


def resample_indices(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Step 11: draw N copies from each row's weight CDF, systematically.

    The N keys of a row are (u + j) / N, j = 0 … N - 1, from one uniform u:
    each copy is still drawn from the CDF, but stratified, which resamples
    with less noise than N independent keys (Douc & Cappé 2005), and the
    copies of particle i are simply the keys in [S_{i-1}, S_i), counted in
    one pass instead of N binary searches.

    Parameters
    ----------
    w : ndarray, shape (D, N)
        Weights, rows summing to 1.
    u : ndarray, shape (D,)
        One uniform in [0, 1) per row.

    Returns
    -------
    ndarray of intp, shape (D, N)
        For each key the smallest i with key < S_i, S_k = Σ_{j≤k} w_j; ascending.
    """
    d, n = w.shape
    cdf = np.cumsum(w, axis=-1)
    # keys below S_i: #{j : (u + j) / N < S_i} = ⌈N S_i - u⌉, within [0, N]
    below = np.clip(np.ceil(n * cdf - np.asarray(u)[:, None]), 0, n).astype(np.intp)
    # S_N is 1 up to rounding: every key lies below it
    below[:, -1] = n
    copies = np.diff(below, axis=-1, prepend=0)
    flat = np.repeat(np.arange(d * n), copies.ravel())
    return flat.reshape(d, n) - (np.arange(d) * n)[:, None]


RADIUS_BINS_PER_EFOLD = 32
"""Bins of the radius quantile per factor e of distance: 3% resolution."""
RADIUS_BIN_FLOOR_M = 0.05
"""Distances are binned as ln(1 + d / floor): 5 cm resolution near zero."""
RADIUS_BINS = 320
"""Number of bins: up to 0.05 (e¹⁰ - 1) ≈ 1.1 km."""


def weighted_radius(
    x: np.ndarray, y: np.ndarray, w: np.ndarray, cx: np.ndarray, cy: np.ndarray, q: float
) -> np.ndarray:
    """Return the radius about (cx, cy) holding weight fraction ``q`` of each row's particles.

    Distances are binned 3% wide on a log scale and the upper edge of the
    bin where the cumulative weight reaches ``q`` is returned: sorting each
    row costs five times more.

    Parameters
    ----------
    x, y, w : ndarray, shape (D, N)
    cx, cy : ndarray, shape (D,)
    q : float
        Fraction in (0, 1].
    """
    d, n = x.shape
    # in the particles' float32: a float64 centre would promote every temporary
    dx = x - np.asarray(cx, np.float32)[:, None]
    dy = y - np.asarray(cy, np.float32)[:, None]
    dist = np.sqrt(dx * dx + dy * dy)
    # bin = ⌊k ln(1 + d / d₀)⌋
    scale = np.float32(1.0 / RADIUS_BIN_FLOOR_M)
    b = (np.float32(RADIUS_BINS_PER_EFOLD) * np.log1p(dist * scale)).astype(np.intp)
    np.minimum(b, RADIUS_BINS - 1, out=b)
    b += np.arange(d)[:, None] * RADIUS_BINS
    hist = np.bincount(b.ravel(), weights=w.ravel(), minlength=d * RADIUS_BINS)
    cum = np.cumsum(hist.reshape(d, RADIUS_BINS), axis=-1)
    k = np.argmax(cum >= q * cum[:, -1:] * (1.0 - 1e-12), axis=-1)
    # upper edge: d₀ (e^((k + 1) / k_e) - 1)
    return RADIUS_BIN_FLOOR_M * np.expm1((k + 1) / RADIUS_BINS_PER_EFOLD)


# --- storage and the batched update -------------------------------------------------


class ParticleBank:
    """Stacked storage for many floor filters: row ``slot`` of each array is one filter.

    Attributes
    ----------
    x, y, alpha : ndarray of float32, shape (S, N)
        Positions (m) and directions (rad clockwise from +y).
    w : ndarray of float64, shape (S, N)
        Weights.
    sampled : ndarray of bool, shape (S,)
        Whether step 1 has run.
    last_radio, last_weights : ndarray of int64, shape (S,)
        Time (ms) of the last window with readings and of the last weight update.
    radius : ndarray of float64, shape (S,)
        68% radius (m) at the last update, the indoor radius of the fix pull.
    """

    _ROWS = ("x", "y", "alpha", "w")
    _SCALARS = ("sampled", "last_radio", "last_weights", "radius")

    def __init__(self, n_particles: int, capacity: int = 8) -> None:
        self.n = n_particles
        self.x = np.zeros((0, n_particles), np.float32)
        self.y = np.zeros((0, n_particles), np.float32)
        self.alpha = np.zeros((0, n_particles), np.float32)
        self.w = np.zeros((0, n_particles), np.float64)
        self.sampled = np.zeros(0, bool)
        self.last_radio = np.zeros(0, np.int64)
        self.last_weights = np.zeros(0, np.int64)
        self.radius = np.zeros(0)
        self._free: list[int] = []
        self._grow(capacity)

    def _grow(self, capacity: int) -> None:
        old = self.x.shape[0]
        if capacity <= old:
            return
        for name in self._ROWS:
            a = getattr(self, name)
            b = np.zeros((capacity, self.n), a.dtype)
            b[:old] = a
            setattr(self, name, b)
        for name in self._SCALARS:
            a = getattr(self, name)
            b = np.zeros(capacity, a.dtype)
            b[:old] = a
            setattr(self, name, b)
        self._free.extend(range(capacity - 1, old - 1, -1))

    def allocate(self) -> int:
        """Return a fresh, never-sampled slot."""
        if not self._free:
            self._grow(max(8, 2 * self.x.shape[0]))
        slot = self._free.pop()
        self.sampled[slot] = False
        self.last_radio[slot] = NEVER
        self.last_weights[slot] = NEVER
        self.radius[slot] = np.inf
        return slot

    def release(self, slot: int) -> None:
        """Return a slot to the pool."""
        self._free.append(slot)

    def export(self, slot: int) -> dict[str, Any]:
        """Return a copy of one filter's state as arrays and scalars."""
        out: dict[str, Any] = {name: getattr(self, name)[slot].copy() for name in self._ROWS}
        out["sampled"] = bool(self.sampled[slot])
        out["last_radio"] = int(self.last_radio[slot])
        out["last_weights"] = int(self.last_weights[slot])
        out["radius"] = float(self.radius[slot])
        return out

    def restore(self, state: dict[str, Any]) -> int:
        """Allocate a slot holding an exported state exactly."""
        slot = self.allocate()
        for name in self._ROWS:
            getattr(self, name)[slot] = np.asarray(state[name])
        self.sampled[slot] = bool(state["sampled"])
        self.last_radio[slot] = int(state["last_radio"])
        self.last_weights[slot] = int(state["last_weights"])
        self.radius[slot] = float(state["radius"])
        return slot


@dataclass(frozen=True, eq=False)
class FilterInput:
    """One filter's inputs for one positioning window.

    Attributes
    ----------
    slot : int
        Row of the filter in the bank.
    t : int
        Window time (ms).
    tx, rssi, count : ndarray, shape (M,)
        Site transmitter index, mean RSSI (dBm) and reading count of each
        transmitter of this floor heard in the window.
    step_length, step_heading : ndarray, shape (K,)
        The window's steps: length (m) and heading (deg clockwise from +y, NaN unknown).
    walk_s : float
        Seconds of random-walk motion to apply when the device has no
        inertial stream; 0 otherwise.
    fix : tuple of float, optional
        Positional measurement (x, y, radius in m), already on this floor.
    rng : np.random.Generator
        The device's generator.
    """

    slot: int
    t: int
    tx: np.ndarray
    rssi: np.ndarray
    count: np.ndarray
    rng: np.random.Generator
    step_length: np.ndarray = field(default_factory=lambda: np.zeros(0))
    step_heading: np.ndarray = field(default_factory=lambda: np.zeros(0))
    walk_s: float = 0.0
    fix: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class FilterEstimate:
    """A filter's position after an update: weighted mean, direction and spread.

    ``heading`` is degrees clockwise from +y in [0, 360), NaN when the
    particle directions are too spread to mean anything (mean resultant
    length below 0.5); ``radius`` is the 68% radius (m) about (x, y);
    ``resampled`` whether step 11 ran.
    """

    x: float
    y: float
    heading: float
    radius: float
    resampled: bool


def update_filters(
    bank: ParticleBank,
    model: FloorModel,
    inputs: Sequence[FilterInput],
    params: ParticleFilterParams,
) -> list[FilterEstimate]:
    """Run steps 1–11 for filters of one floor, ``params.chunk`` filters per numpy call."""
    out: list[FilterEstimate] = []
    for start in range(0, len(inputs), params.chunk):
        out.extend(_update_chunk(bank, model, inputs[start : start + params.chunk], params))
    return out


@dataclass
class _Draws:
    """One chunk's phase-A random numbers, drawn per device in input order.

    Each array holds only the rows that need it: ``scatter`` the rescattered
    filters, ``motion`` the moving ones, ``mutate`` and ``centre`` those
    running steps 7–9, in the order of the chunk.
    """

    scatter: np.ndarray
    motion: np.ndarray
    mutate: np.ndarray
    centre: np.ndarray


def _draw(
    inputs: Sequence[FilterInput],
    rescatter: np.ndarray,
    moving: np.ndarray,
    mutate: np.ndarray,
    p: ParticleFilterParams,
) -> _Draws:
    """Draw what each filter needs this update from its own device's generator."""
    n = p.n_particles
    draws = _Draws(
        scatter=np.empty((int(rescatter.sum()), n, 4)),
        motion=np.empty((int(moving.sum()), 2, n), np.float32),
        mutate=np.empty((int(mutate.sum()), 5 * p.n_mutate + 2 * p.n_centre)),
        centre=np.empty((int(mutate.sum()), 2, p.n_centre)),
    )
    i_s = i_m = i_u = 0
    for r, inp in enumerate(inputs):
        rng = inp.rng
        if rescatter[r]:
            rng.random(out=draws.scatter[i_s])
            i_s += 1
        if moving[r]:
            rng.random(out=draws.motion[i_m], dtype=np.float32)
            i_m += 1
        if mutate[r]:
            rng.random(out=draws.mutate[i_u])
            rng.standard_normal(out=draws.centre[i_u])
            i_u += 1
    return draws


def _steps_table(inputs: list[FilterInput]) -> tuple[np.ndarray, np.ndarray]:
    """Return (R, K) step lengths (0 padded) and headings in rad (last heading repeated)."""
    width = max(1, max(i.step_length.size for i in inputs))
    length = np.zeros((len(inputs), width))
    heading = np.zeros((len(inputs), width))
    for r, inp in enumerate(inputs):
        k = inp.step_length.size
        length[r, :k] = inp.step_length
        heading[r, :k] = np.radians(inp.step_heading)
        heading[r, k:] = heading[r, k - 1] if k else np.nan
    return length, heading


def _move(
    model: FloorModel,
    x: np.ndarray,
    y: np.ndarray,
    alpha: np.ndarray,
    inputs: list[FilterInput],
    noise: np.ndarray,
    p: ParticleFilterParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2 for moving filters: the window's move of every particle, checked against the plan.

    A blocked particle stays put and takes the random direction (2u - 1) π
    from the uniform that drew its heading error: that draw only shaped the
    move it did not make, so it is still an independent uniform.
    """
    noise_t = noise.transpose(1, 0, 2)
    walking = np.array([i.step_length.size == 0 for i in inputs])
    # rows whose moves may exceed max_move_m: random walks, and windows of many steps
    # (a step's length error is at most √3 σ_L)
    error = np.sqrt(3.0) * p.step_length_std_m
    longest = np.array([i.step_length.sum() + i.step_length.size * error for i in inputs])
    may_be_long = walking | (longest > p.max_move_m)
    dx = np.empty(alpha.shape, np.float32)
    dy = np.empty(alpha.shape, np.float32)
    direction = np.empty(alpha.shape, np.float32)
    for rows, walk in ((np.flatnonzero(~walking), False), (np.flatnonzero(walking), True)):
        if rows.size == 0:
            continue
        chosen = [inputs[r] for r in rows]
        if walk:
            dt = np.array([[i.walk_s] for i in chosen])
            out = walk_displacement(dt, alpha[rows], noise_t[:, rows], p)
        else:
            length, heading = _steps_table(chosen)
            out = window_displacement(length, heading, alpha[rows], noise_t[:, rows], p)
        dx[rows], dy[rows], direction[rows] = out
    # moves longer than max_move_m are shortened to it
    rows = np.flatnonzero(may_be_long)
    if rows.size:
        norm = np.hypot(dx[rows], dy[rows])
        scale = np.minimum(1.0, np.float32(p.max_move_m) / np.maximum(norm, 1e-6))
        dx[rows] *= scale
        dy[rows] *= scale
    nx, ny = x + dx, y + dy
    ok = moves_free(model.walls, x, y, nx, ny)
    x = np.where(ok, nx, x)
    y = np.where(ok, ny, y)
    # α = θ for a made move, (2u - 1) π for a blocked one
    alpha = np.where(ok, direction, (2.0 * noise_t[1] - 1.0) * np.float32(np.pi))
    return x, y, alpha


def _pull(
    model: FloorModel, x: np.ndarray, y: np.ndarray, fix: np.ndarray, r_pf: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Step 2: shift particles towards positional measurements (R, 3: x, y, radius).

    The shift is the fraction ρ / (1 + ρ) of the way, ρ = r_indoor / r_fix:
    proportional to the patent's ratio of radii while small and never past
    the measurement. The measurement is first projected onto the free area;
    a particle the shift would put on a blocked cell stays where it is.
    """
    fxy = model.plan.project(fix[:, :2])
    # k = r_pf / (r_pf + r_fix); a filter without a radius yet jumps to the fix
    k = np.where(np.isfinite(r_pf), r_pf / (r_pf + fix[:, 2]), 1.0)[:, None]
    px = x + k * (fxy[:, :1] - x)
    py = y + k * (fxy[:, 1:] - y)
    ok = model.plan.is_free(np.stack([px, py], axis=-1))
    return np.where(ok, px, x), np.where(ok, py, y)


def mutation(
    model: FloorModel, u: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 7: which particles to rescatter and where.

    Parameters
    ----------
    u : ndarray, shape (R, 5 N_m)
        Uniforms: N_m particle picks (with replacement, "choose a random
        particle" N_m times), then 4 N_m scatter uniforms.
    n : int
        Particles per filter.

    Returns
    -------
    index, x, y, alpha : ndarray, shape (R, N_m)
    """
    m = u.shape[1] // 5
    pick = (u[:, :m] * n).astype(np.intp)
    # (R, 4 N_m) → (R, N_m, 4); the row count is explicit so that N_m = 0 reshapes too
    x, y, alpha = scatter(model, u[:, m:].reshape(u.shape[0], 4, m).transpose(0, 2, 1))
    return pick, x, y, alpha


def centre_sampling(
    model: FloorModel,
    centre: np.ndarray,
    u: np.ndarray,
    g: np.ndarray,
    params: ParticleFilterParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 9: N_c random particles around the sampling centre.

    Parameters
    ----------
    centre : ndarray, shape (R, 2)
        Sampling centre (m) of each filter.
    u : ndarray, shape (R, 2 N_c)
        Uniforms: N_c particle picks, then N_c directions.
    g : ndarray, shape (R, 2, N_c)
        Standard normals for x and y.

    Returns
    -------
    index, x, y, alpha : ndarray, shape (R, N_c)
        Positions ~ N(centre, d_ce I) projected onto the free area; α uniform.
    """
    c = u.shape[1] // 2
    pick = (u[:, :c] * params.n_particles).astype(np.intp)
    # (x, y) = centre + √d_ce g
    xy = centre[:, None, :] + np.sqrt(params.centre_variance_m2) * g.transpose(0, 2, 1)
    xy = model.plan.project(xy)
    # α = (2u - 1) π
    alpha = (2.0 * u[:, c:] - 1.0) * np.pi
    return pick, xy[..., 0], xy[..., 1], alpha


def _mutate_and_centre(
    model: FloorModel,
    x: np.ndarray,
    y: np.ndarray,
    alpha: np.ndarray,
    w: np.ndarray,
    tx: np.ndarray,
    rssi: np.ndarray,
    valid: np.ndarray,
    u: np.ndarray,
    g: np.ndarray,
    p: ParticleFilterParams,
) -> None:
    """Steps 7–9 in place on rows of (R, N) arrays; new particles get w = 1/N.

    ``u`` (R, 5 N_m + 2 N_c) uniforms for :func:`mutation` then
    :func:`centre_sampling`; ``g`` (R, 2, N_c) normals.
    """
    n, m = p.n_particles, p.n_mutate
    rows = np.arange(x.shape[0])[:, None]
    pick, mx, my, ma = mutation(model, u[:, : 5 * m], n)
    x[rows, pick], y[rows, pick], alpha[rows, pick] = mx, my, ma
    w[rows, pick] = 1.0 / n
    nearest = sampling_centre(rssi, model.A[tx], model.B[tx], valid)
    centre = model.xy[tx[rows[:, 0], nearest]]
    pick, cx, cy, ca = centre_sampling(model, centre, u[:, 5 * m :], g, p)
    x[rows, pick], y[rows, pick], alpha[rows, pick] = cx, cy, ca
    w[rows, pick] = 1.0 / n


def _estimate(
    x: np.ndarray, y: np.ndarray, alpha: np.ndarray, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return each row's weighted mean x, y, mean direction (deg) and 68% radius."""
    # float32 weights keep the sums in the particles' type (millimetres at a kilometre)
    w32 = w.astype(np.float32)
    mx = np.einsum("dn,dn->d", w32, x).astype(float)
    my = np.einsum("dn,dn->d", w32, y).astype(float)
    s = np.einsum("dn,dn->d", w32, np.sin(alpha)).astype(float)
    co = np.einsum("dn,dn->d", w32, np.cos(alpha)).astype(float)
    # mean direction atan2(Σ w sin α, Σ w cos α), kept when the resultant R ≥ 0.5
    heading = np.where(np.hypot(s, co) >= 0.5, np.mod(np.degrees(np.arctan2(s, co)), 360.0), np.nan)
    return mx, my, heading, weighted_radius(x, y, w, mx, my, 0.68)


def _select(mask: np.ndarray) -> slice | np.ndarray:
    """Return an index for the rows where ``mask`` holds: a slice (views) when it holds for all."""
    return slice(None) if mask.all() else np.flatnonzero(mask)


def _readings_table(
    model: FloorModel, inputs: Sequence[FilterInput]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 4: (D, M) tables of the usable transmitters heard: index, mean RSSI, count, valid."""
    sizes = np.array([i.tx.size for i in inputs])
    tx = np.concatenate([i.tx for i in inputs]).astype(np.intp)
    row = np.repeat(np.arange(len(inputs)), sizes)
    rssi = np.concatenate([i.rssi for i in inputs])
    keep = model.usable[tx] & np.isfinite(rssi)
    tx, row, rssi = tx[keep], row[keep], rssi[keep]
    count = np.concatenate([i.count for i in inputs])[keep]
    kept = np.bincount(row, minlength=len(inputs))
    width = max(1, int(kept.max(initial=0)))
    # column = position of the reading within its row
    col = np.arange(row.size) - np.repeat(np.cumsum(kept) - kept, kept)
    shape = (len(inputs), width)
    tables = (np.zeros(shape, np.intp), np.zeros(shape), np.zeros(shape), np.zeros(shape, bool))
    tables[0][row, col], tables[1][row, col], tables[2][row, col] = tx, rssi, count
    tables[3][row, col] = True
    return tables


def _update_chunk(
    bank: ParticleBank,
    model: FloorModel,
    inputs: Sequence[FilterInput],
    p: ParticleFilterParams,
) -> list[FilterEstimate]:
    n = p.n_particles
    slots = np.array([i.slot for i in inputs], dtype=np.intp)
    t = np.array([i.t for i in inputs], dtype=np.int64)
    # consecutive slots are worked on in place, others copied out and back
    contiguous = bool(np.all(np.diff(slots) == 1))
    where = slice(int(slots[0]), int(slots[-1]) + 1) if contiguous else slots
    x, y, alpha, w = bank.x[where], bank.y[where], bank.alpha[where], bank.w[where]

    tx, rssi, count, valid = _readings_table(model, inputs)
    radio = np.array([i.tx.size > 0 for i in inputs])

    # Decisions that depend only on the state before the move.
    stale = ~bank.sampled[slots] | (t - bank.last_radio[slots] > p.rescatter_after_ms)
    starving = ~stale & (alive_count(w, p.dead_weight) < p.min_alive)
    weigh = (t - bank.last_weights[slots] >= p.update_interval_ms) & valid.any(axis=1)
    mutate = weigh & (valid.sum(axis=1) >= p.min_transmitters)
    moving = np.array([i.step_length.size > 0 or i.walk_s > 0 for i in inputs])
    draws = _draw(inputs, stale | starving, moving, mutate, p)
    scatter_rows = np.cumsum(stale | starving) - 1

    # Step 1.
    rows = np.flatnonzero(stale)
    if rows.size:
        x[rows], y[rows], alpha[rows] = scatter(model, draws.scatter[scatter_rows[rows]])
        w[rows] = 1.0 / n

    # Step 2: motion, then the pull of positional measurements.
    if moving.any():
        rows = _select(moving)
        x[rows], y[rows], alpha[rows] = _move(
            model,
            x[rows],
            y[rows],
            alpha[rows],
            [i for i, m in zip(inputs, moving, strict=True) if m],
            draws.motion,
            p,
        )
    pulled = np.array([i.fix is not None for i in inputs])
    if pulled.any():
        rows = np.flatnonzero(pulled)
        fix = np.array([inputs[r].fix for r in rows], dtype=float)
        x[rows], y[rows] = _pull(model, x[rows], y[rows], fix, bank.radius[slots[rows]])

    # Step 3.
    rows = np.flatnonzero(starving)
    if rows.size:
        x[rows], y[rows], alpha[rows] = scatter(model, draws.scatter[scatter_rows[rows]])
        w[rows] = 1.0 / n

    # Steps 5–9.
    if mutate.any():
        rows = _select(mutate)
        xr, yr, ar, wr = x[rows], y[rows], alpha[rows], w[rows]
        _mutate_and_centre(
            model,
            xr,
            yr,
            ar,
            wr,
            tx[rows],
            rssi[rows],
            valid[rows],
            draws.mutate,
            draws.centre,
            p,
        )
        x[rows], y[rows], alpha[rows], w[rows] = xr, yr, ar, wr

    # Step 10.
    if weigh.any():
        rows = _select(weigh)
        ok = valid[rows]
        sigma = np.where(ok, model.sigma[tx[rows]], 1.0)
        # c_m = n_m / (2 σ_m²), zero for padding
        cw = np.where(ok, count[rows] / (2.0 * sigma * sigma), 0.0)
        cells = model.grid.cell_index(x[rows], y[rows])
        local = np.maximum(model.local[tx[rows]], 0)
        w[rows] = reweight(w[rows], grid_log_likelihood(model.grid, cells, local, rssi[rows], cw))
        bank.last_weights[slots[rows]] = t[rows]
    bank.last_radio[slots[radio]] = t[radio]

    # Step 11: the device draws its uniform only when it resamples.
    resample = needs_resampling(w, p.resample_n)
    if resample.any():
        picked = np.flatnonzero(resample)
        u = np.array([inputs[r].rng.random() for r in picked])
        # copies of row r come from row r: flat index r·N + i
        flat = (resample_indices(w[picked], u) + picked[:, None] * n).ravel()
        x[picked] = x.ravel().take(flat).reshape(-1, n)
        y[picked] = y.ravel().take(flat).reshape(-1, n)
        alpha[picked] = alpha.ravel().take(flat).reshape(-1, n)
        w[picked] = 1.0 / n

    mx, my, heading, radius = _estimate(x, y, alpha, w)
    if not contiguous:
        bank.x[slots], bank.y[slots], bank.alpha[slots], bank.w[slots] = x, y, alpha, w
    bank.sampled[slots] = True
    bank.radius[slots] = radius
    return [
        FilterEstimate(float(mx[r]), float(my[r]), float(heading[r]), float(radius[r]), bool(s))
        for r, s in enumerate(resample)
    ]


class ParticleFilter:
    """One floor's filter on its own: a thin wrapper over a one-row bank.

    Parameters
    ----------
    model : FloorModel
        The floor (``build_floor_models``).
    params : ParticleFilterParams
    rng : np.random.Generator
        The device's generator.
    state : dict, optional
        A :meth:`snapshot` to resume from.
    """

    def __init__(
        self,
        model: FloorModel,
        params: ParticleFilterParams,
        rng: np.random.Generator,
        state: dict[str, Any] | None = None,
    ) -> None:
        self.model = model
        self.params = params
        self.rng = rng
        self.bank = ParticleBank(params.n_particles, capacity=1)
        self.slot = self.bank.restore(state) if state is not None else self.bank.allocate()

    def update(
        self,
        t: int,
        tx: np.ndarray,
        rssi: np.ndarray,
        count: np.ndarray | None = None,
        *,
        step_length: np.ndarray | None = None,
        step_heading: np.ndarray | None = None,
        walk_s: float = 0.0,
        fix: tuple[float, float, float] | None = None,
    ) -> FilterEstimate:
        """Run one update with one window's per-transmitter readings and motion."""
        tx = np.asarray(tx, dtype=np.intp)
        inp = FilterInput(
            slot=self.slot,
            t=int(t),
            tx=tx,
            rssi=np.asarray(rssi, dtype=float),
            count=np.ones(tx.size) if count is None else np.asarray(count, dtype=float),
            rng=self.rng,
            step_length=np.zeros(0) if step_length is None else np.asarray(step_length, float),
            step_heading=np.zeros(0) if step_heading is None else np.asarray(step_heading, float),
            walk_s=walk_s,
            fix=fix,
        )
        return update_filters(self.bank, self.model, [inp], self.params)[0]

    def snapshot(self) -> dict[str, Any]:
        """Return the particles and bookkeeping (the generator is the caller's)."""
        return self.bank.export(self.slot)

    @property
    def particles(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Views of x, y, α and w of this filter, shape (N,) each."""
        s = self.slot
        return self.bank.x[s], self.bank.y[s], self.bank.alpha[s], self.bank.w[s]
