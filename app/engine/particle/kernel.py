"""Compiled loops for the per-particle work of an update: moves, likelihood, resampling, estimate.

Each function here has a numpy twin elsewhere in the package (the
reference) with the same signature and, by construction, the same result
(but for the estimate's float64 sums, 10⁻¹¹ m apart as they run in another
order): the loops do the twin's float32 and float64 arithmetic in the same
order, and every transcendental (sin, cos, exp) is still taken by
numpy's vectorised ufuncs between the loops. numba's scalar libm calls
differ from numpy's SIMD loops in the last bit for some float32 inputs
and cost many times more; a last-bit difference in a particle's position
decides, now and then, which cell or side of a wall it is on, and
resampling turns that into a different track. What stays numpy is a few
passes over contiguous rows; what is compiled is what numpy does badly:
the wall trace's data-dependent loop, the likelihood's once-per-occupied-
cell gather, resampling's copies and the radius histogram.

The loops are compiled once per process and cached on disk.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from app.engine.particle.estimate import (
    RADIUS_BIN_FLOOR_M,
    RADIUS_BINS,
    RADIUS_BINS_PER_EFOLD,
    RADIUS_EDGES,
)
from app.engine.particle.floor_model import FloorModel
from app.engine.particle.inputs import FilterInput
from app.engine.particle.motion import (
    Moves,
    displacements,
    error_scales,
    heading_sums,
    walk_scales,
    window_displacement,
)
from app.engine.particle.params import ParticleFilterParams
from app.engine.particle.walls import WallRaster
from app.engine.particle.weights import reading_weights

_ROOT2 = np.float32(np.sqrt(2.0))
_PI = np.float32(np.pi)
_ONE = np.float32(1.0)
_TWO = np.float32(2.0)
_HALF = np.float32(0.5)
_TINY = np.float32(1e-6)


def move_particles(
    model: FloorModel,
    x: np.ndarray,
    y: np.ndarray,
    alpha: np.ndarray,
    inputs: list[FilterInput],
    noise: np.ndarray,
    p: ParticleFilterParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2 for moving filters, as ``motion.move_particles``, moves and checks compiled."""
    dx, dy, direction, long = displacements(
        alpha, inputs, noise, p, walk=walk_moves, window=window_moves
    )
    return settle_moves(model, x, y, dx, dy, direction, noise[:, 1], long, p.max_move_m)


def window_moves(
    length: np.ndarray,
    heading: np.ndarray,
    alpha: np.ndarray,
    noise: np.ndarray,
    p: ParticleFilterParams,
) -> Moves:
    """Step 2 for windows of steps, as ``motion.window_displacement``.

    One compiled pass for the errors, numpy's sin and cos, one pass for the
    moves; rows with a step without a heading take the reference's path.
    """
    if np.isnan(heading).any():
        return window_displacement(length, heading, alpha, noise, p)
    vx, vy, ux, uy, last = heading_sums(length, heading)
    length_scale, heading_scale = error_scales(p)
    turn = _heading_errors(noise, heading_scale)
    return _window_moves(
        noise, turn, np.sin(turn), np.cos(turn), vx, vy, ux, uy, last, length_scale
    )


def walk_moves(
    dt_s: np.ndarray, alpha: np.ndarray, noise: np.ndarray, p: ParticleFilterParams
) -> Moves:
    """Step 2 for random walks, as ``motion.walk_displacement``.

    A compiled pass for the directions and steps, numpy's sin and cos, a
    compiled pass for the moves.
    """
    dt, turn_scale, speed_scale = walk_scales(dt_s, p)
    direction, step = _walk_directions(alpha, noise, dt, turn_scale, speed_scale)
    return (*_scaled(step, np.sin(direction), np.cos(direction)), direction)


@njit(cache=True)
def _walk_directions(
    alpha: np.ndarray,
    noise: np.ndarray,
    dt: np.ndarray,
    turn_scale: np.ndarray,
    speed_scale: np.float32,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Return α + (2u - 1) √3 σ_turn √Δt and σ_v √(2E) Δt of every particle."""
    rows, n = alpha.shape
    direction = np.empty((rows, n), np.float32)
    step = np.empty((rows, n), np.float32)
    for r in range(rows):
        for i in range(n):
            direction[r, i] = alpha[r, i] + (_TWO * noise[1, r, i] - _ONE) * turn_scale[r, 0]
            step[r, i] = speed_scale * np.sqrt(_TWO * noise[0, r, i]) * dt[r, 0]
    return direction, step


@njit(cache=True)
def _scaled(
    step: np.ndarray, sin_a: np.ndarray, cos_a: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Return step · sin α and step · cos α."""
    rows, n = step.shape
    dx = np.empty((rows, n), np.float32)
    dy = np.empty((rows, n), np.float32)
    for r in range(rows):
        for i in range(n):
            dx[r, i] = step[r, i] * sin_a[r, i]
            dy[r, i] = step[r, i] * cos_a[r, i]
    return dx, dy


@njit(cache=True)
def _heading_errors(noise: np.ndarray, scale: np.float32) -> np.ndarray:  # pragma: no cover
    """Return ε_θ = (2u - 1) √3 σ_θ of every particle from its uniform ``noise[1]``."""
    _, rows, n = noise.shape
    out = np.empty((rows, n), np.float32)
    for r in range(rows):
        for i in range(n):
            out[r, i] = (_TWO * noise[1, r, i] - _ONE) * scale
    return out


@njit(cache=True)
def _window_moves(
    noise: np.ndarray,
    turn: np.ndarray,
    sin_t: np.ndarray,
    cos_t: np.ndarray,
    vx: np.ndarray,
    vy: np.ndarray,
    ux: np.ndarray,
    uy: np.ndarray,
    last: np.ndarray,
    length_scale: np.float32,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Return Δ = (V + ε_L U) rotated clockwise by ε_θ, and α = θ_last + ε_θ, per particle."""
    rows, n = turn.shape
    dx = np.empty((rows, n), np.float32)
    dy = np.empty((rows, n), np.float32)
    direction = np.empty((rows, n), np.float32)
    for r in range(rows):
        for i in range(n):
            error = (_TWO * noise[0, r, i] - _ONE) * length_scale
            a = vx[r, 0] + error * ux[r, 0]
            b = vy[r, 0] + error * uy[r, 0]
            c, s = cos_t[r, i], sin_t[r, i]
            dx[r, i] = a * c + b * s
            dy[r, i] = b * c - a * s
            direction[r, i] = last[r, 0] + turn[r, i]
    return dx, dy, direction


def settle_moves(
    model: FloorModel,
    x: np.ndarray,
    y: np.ndarray,
    dx: np.ndarray,
    dy: np.ndarray,
    direction: np.ndarray,
    turn: np.ndarray,
    long: np.ndarray,
    max_move_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2, as ``motion.settle_moves``: the allowed moves made, blocked particles turned."""
    x, y, alpha = x.copy(), y.copy(), np.empty_like(direction)
    walls = model.walls
    _settle(
        x,
        y,
        alpha,
        dx,
        dy,
        direction,
        turn,
        long,
        np.float32(max_move_m),
        walls.clearance,
        walls.stride,
        *_cell_transform(walls),
    )
    return x, y, alpha


def _cell_transform(walls: WallRaster) -> tuple[np.float32, np.float32, np.float32]:
    """Return (1 / c, x₀ / c - pad, y₀ / c - pad) in float32, as ``WallRaster.cells`` uses them."""
    inv = walls.inv_cell
    return (
        np.float32(inv),
        np.float32(walls.origin[0] * inv - walls.pad),
        np.float32(walls.origin[1] * inv - walls.pad),
    )


@njit(cache=True)
def _settle(
    x: np.ndarray,
    y: np.ndarray,
    alpha: np.ndarray,
    dx: np.ndarray,
    dy: np.ndarray,
    direction: np.ndarray,
    turn: np.ndarray,
    long: np.ndarray,
    max_move: np.float32,
    clearance: np.ndarray,
    stride: int,
    inv: np.float32,
    off_u: np.float32,
    off_v: np.float32,
) -> None:  # pragma: no cover - compiled
    """Make each particle's move in place where the plan allows it, as ``motion.settle_moves``.

    ``walls.moves_free``'s rule in two passes: the ends of every move, which
    settle most of them, then the sphere trace of the moves neither end
    vouches for, in rounds of one point of each move still traced. Neither
    pass branches on the data: a branch on whether a move needs tracing, or
    on whether a point ends it, would be mispredicted about every other time.
    """
    rows, n = x.shape
    # (0.999 L)²: float32's |Δ|² errs by far less than that 0.2%
    near_max = np.float32(0.999) * max_move * (np.float32(0.999) * max_move)
    # the moves to trace: start and step (cells), points per cell, next and last point
    su = np.empty(rows * n, np.float32)
    sv = np.empty(rows * n, np.float32)
    tu = np.empty(rows * n, np.float32)
    tv = np.empty(rows * n, np.float32)
    per_cell = np.empty(rows * n, np.float32)
    at = np.empty(rows * n, np.float32)
    last = np.empty(rows * n, np.float32)
    which = np.empty(rows * n, np.int64)
    traced = 0
    for r in range(rows):
        for i in range(n):
            sx, sy = dx[r, i], dy[r, i]
            # a move well within L keeps s = 1 (L / |Δ| ≥ 1): only a long one needs |Δ|
            if long[r] and sx * sx + sy * sy > near_max:
                # |Δ| = hypot(Δx, Δy), glibc's way: rounded once from float64, where
                # the squares are exact (a libm call costs five times more)
                norm = np.float32(np.sqrt(np.float64(sx) ** 2 + np.float64(sy) ** 2))
                # shortened to max_move: s = min(1, L / max(|Δ|, 10⁻⁶))
                scale = min(_ONE, max_move / max(norm, _TINY))
                sx *= scale
                sy *= scale
            x0, y0 = x[r, i], y[r, i]
            x1, y1 = x0 + sx, y0 + sy
            # u = x / c - (x₀ / c - pad)
            u0, v0 = x0 * inv - off_u, y0 * inv - off_v
            u1, v1 = x1 * inv - off_u, y1 * inv - off_v
            du, dv = u1 - u0, v1 - v0
            length = np.sqrt(du * du + dv * dv)
            k1 = int(v1) * stride + int(u1)
            # a cell is free where its clearance is positive (at least a cell)
            clear1 = clearance[k1]
            end_free = clear1 > np.float32(0.0)
            reach0 = clearance[int(v0) * stride + int(u0)] - _ROOT2
            reach1 = clear1 - _ROOT2
            # free ⇐ every point lies within the reach of one end
            made = end_free & (reach0 + reach1 > length)
            trace = end_free & ~made
            # blocked: α = (2u - 1) π; a traced move is settled after the trace
            x[r, i] = x1 if made else x0
            y[r, i] = y1 if made else y0
            alpha[r, i] = direction[r, i] if made else (_TWO * turn[r, i] - _ONE) * _PI
            # walls.trace_span: k = ⌈|move| / ½⌉ points after the start, those an end
            # vouches for skipped
            k = max(np.ceil(_TWO * length), _ONE)
            inv_h = k / max(length, _TINY)
            # written for every move, kept (traced advanced) for those to trace
            at[traced] = max(np.ceil(reach0 * inv_h), _ONE)
            last[traced] = np.floor(min(k - reach1 * inv_h, k - _HALF))
            tu[traced], tv[traced] = du / k, dv / k
            su[traced], sv[traced] = u0, v0
            per_cell[traced] = inv_h
            which[traced] = r * n + i
            dx[r, i], dy[r, i] = sx, sy
            traced += trace
    # walls._trace_moves: point j = p₀ + j Δp / k, looked up, vouches for ⌈(c - √2) k / |Δ|⌉
    good = np.ones(traced, np.bool_)
    active = np.empty(traced, np.int64)
    count = 0
    for m in range(traced):
        active[count] = m
        count += at[m] <= last[m]
    top = clearance.size - 1
    while count:
        kept = 0
        for q in range(count):
            m = active[q]
            j = at[m]
            c = clearance[
                min(max(int(sv[m] + j * tv[m]) * stride + int(su[m] + j * tu[m]), 0), top)
            ]
            ok = c > np.float32(0.0)
            good[m] = ok
            j = j + max(np.ceil((c - _ROOT2) * per_cell[m]), _ONE)
            at[m] = j
            active[kept] = m
            kept += ok & (j <= last[m])
        count = kept
    x, y, alpha = x.reshape(-1), y.reshape(-1), alpha.reshape(-1)
    dx, dy, direction = dx.reshape(-1), dy.reshape(-1), direction.reshape(-1)
    for m in range(traced):
        f = which[m]
        if good[m]:
            x[f] += dx[f]
            y[f] += dy[f]
            alpha[f] = direction[f]


def log_likelihood(
    model: FloorModel,
    x: np.ndarray,
    y: np.ndarray,
    tx: np.ndarray,
    rssi: np.ndarray,
    count: np.ndarray,
    valid: np.ndarray,
) -> np.ndarray:
    """Step 10, as ``weights.log_likelihood``: one pass, each occupied cell summed once per row.

    A particle on a cell its row has not visited yet sums the readings
    there, in column order, as ``pathloss.grid_log_likelihood`` does; the
    others copy that sum.
    """
    grid = model.grid
    local, weight = reading_weights(model, tx, count, valid)
    step = grid.step_db
    # s' = (s̄ - floor) / step; c' = -step² n_m / (2 σ_m²)
    s_code = ((rssi - grid.floor_dbm) / step).astype(np.float32)
    c = (-weight * step * step).astype(np.float32)
    ny, nx = grid.shape
    return _cell_log_likelihood(
        grid.codes,
        nx,
        ny,
        np.float32(grid.origin[0]),
        np.float32(grid.origin[1]),
        np.float32(1.0 / grid.cell),
        x,
        y,
        local,
        s_code,
        c,
    )


@njit(cache=True)
def _cell_log_likelihood(
    codes: np.ndarray,
    nx: int,
    ny: int,
    x0: np.float32,
    y0: np.float32,
    inv: np.float32,
    x: np.ndarray,
    y: np.ndarray,
    local: np.ndarray,
    s_code: np.ndarray,
    c: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled
    """Return -Σ_m c'_m (code - s'_m)² of each particle's cell, summed once per cell and row.

    A row's occupied cells are listed first and summed after: the raster is
    megabytes, each cell's codes a cache miss, and misses of cells summed in
    a loop of their own overlap, where a sum behind each first visit's
    (mispredicted) branch would wait for its miss alone.
    """
    rows, n = x.shape
    seen = np.full(codes.shape[0], -1, np.int32)
    value = np.empty(codes.shape[0], np.float32)
    cells = np.empty(n, np.int64)
    occupied = np.empty(n, np.int64)
    out = np.empty((rows, n), np.float32)
    for r in range(rows):
        k = 0
        for i in range(n):
            # col = ⌊(x - x₀) / c⌋, row = ⌊(y - y₀) / c⌋, both clamped; k = row · nx + col
            col = min(max(int((x[r, i] - x0) * inv), 0), nx - 1)
            row = min(max(int((y[r, i] - y0) * inv), 0), ny - 1)
            cell = row * nx + col
            cells[i] = cell
            # written for every particle, kept (k advanced) for a cell's first one
            occupied[k] = cell
            k += seen[cell] != r
            seen[cell] = r
        for j in range(k):
            cell = occupied[j]
            ll = np.float32(0.0)
            for m in range(local.shape[1]):
                diff = np.float32(codes[cell, local[r, m]]) - s_code[r, m]
                ll += diff * diff * c[r, m]
            value[cell] = ll
        for i in range(n):
            out[r, i] = value[cells[i]]
    return out


def resample_rows(
    x: np.ndarray,
    y: np.ndarray,
    alpha: np.ndarray,
    w: np.ndarray,
    rows: np.ndarray,
    u: np.ndarray,
) -> None:
    """Step 11 in place, as ``weights.resample_rows``: each copy written once, no index array."""
    _resample(x, y, alpha, w, np.asarray(rows, np.intp), np.asarray(u, np.float64))


@njit(cache=True)
def _resample(
    x: np.ndarray, y: np.ndarray, alpha: np.ndarray, w: np.ndarray, rows: np.ndarray, u: np.ndarray
) -> None:  # pragma: no cover - compiled
    """Copy particle i into the keys (u + j) / N in [S_{i-1}, S_i) of each row, then w = 1/N.

    Key j's particle is the number of i with S_i at or below it, counted as a
    prefix sum of where each S_i falls: no loop over a particle's copies,
    whose count (0, 1 or 2 mostly) would be mispredicted at every particle.
    """
    n = w.shape[1]
    ends = np.empty(n + 1, np.int64)
    bx = np.empty(n, np.float32)
    by = np.empty(n, np.float32)
    ba = np.empty(n, np.float32)
    for q in range(rows.size):
        r = rows[q]
        ends[:] = 0
        cdf = 0.0
        for i in range(n - 1):
            cdf += w[r, i]
            # keys below S_i: ⌈N S_i - u⌉ within [0, N]
            ends[min(max(int(np.ceil(n * cdf - u[q])), 0), n)] += 1
        # every key lies below S_N
        ends[n] += 1
        source = 0
        for j in range(n):
            source += ends[j]
            bx[j], by[j], ba[j] = x[r, source], y[r, source], alpha[r, source]
        x[r], y[r], alpha[r] = bx, by, ba
        w[r] = 1.0 / n


def cloud_estimate(
    x: np.ndarray, y: np.ndarray, alpha: np.ndarray, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return each row's mean x, y, direction and 68% radius, as ``estimate.cloud_estimate``.

    Two compiled passes (the moments and the particles' distances, then the
    radius histogram) around numpy's sin and cos.
    """
    scale = np.float32(1.0 / RADIUS_BIN_FLOOR_M)
    mx, my, s, co, t = _moments(x, y, w, np.sin(alpha), np.cos(alpha), scale)
    k = _quantile_bins(t, w, 0.68, _BIN_BELOW, _EDGES_ABOVE)
    heading = np.where(np.hypot(s, co) >= 0.5, np.mod(np.degrees(np.arctan2(s, co)), 360.0), np.nan)
    # upper edge: d₀ (e^((k + 1) / k_e) - 1)
    return mx, my, heading, RADIUS_BIN_FLOOR_M * np.expm1((k + 1) / RADIUS_BINS_PER_EFOLD)


@njit(cache=True)
def _moments(
    x: np.ndarray,
    y: np.ndarray,
    w: np.ndarray,
    sin_a: np.ndarray,
    cos_a: np.ndarray,
    scale: np.float32,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray
]:  # pragma: no cover - compiled
    """Return each row's Σ w x, Σ w y, Σ w sin α, Σ w cos α and every particle's |p - mean| / d₀."""
    rows, n = x.shape
    mx, my = np.empty(rows), np.empty(rows)
    s, co = np.empty(rows), np.empty(rows)
    scaled = np.empty((rows, n), np.float32)
    for r in range(rows):
        ax = ay = asin = acos = 0.0
        for i in range(n):
            wi = w[r, i]
            ax += wi * x[r, i]
            ay += wi * y[r, i]
            asin += wi * sin_a[r, i]
            acos += wi * cos_a[r, i]
        mx[r], my[r], s[r], co[r] = ax, ay, asin, acos
        # in the particles' float32, as the reference
        cx, cy = np.float32(ax), np.float32(ay)
        for i in range(n):
            ex, ey = x[r, i] - cx, y[r, i] - cy
            scaled[r, i] = np.sqrt(ex * ex + ey * ey) * scale
    return mx, my, s, co, scaled


def _radius_bin_table() -> tuple[np.ndarray, np.ndarray]:
    """Return the radius bin of the least float32 with each top 16 bits, and the edges above.

    The edges are ``RADIUS_EDGES`` followed by NaN. The 16 bits keep 7 of the
    mantissa's: the floats sharing them span 0.8%, less than a bin's 3%, so at
    most one edge lies among them and the bin of any of them is the table's or
    the next, one comparison apart.
    """
    least = (np.arange(1 << 16, dtype=np.uint32) << 16).view(np.float32)
    below = np.searchsorted(RADIUS_EDGES, least, side="right").astype(np.uint16)
    # the last bin has no edge above it: NaN, which no distance reaches
    return below, np.append(RADIUS_EDGES, np.float32(np.nan))


_BIN_BELOW, _EDGES_ABOVE = _radius_bin_table()


@njit(cache=True)
def _quantile_bins(
    t: np.ndarray, w: np.ndarray, q: float, below: np.ndarray, edges: np.ndarray
) -> np.ndarray:  # pragma: no cover - compiled
    """Return each row's first radius bin whose cumulative weight reaches ``q`` of the total.

    A particle's bin, #{b : e_b ≤ t}, is looked up by ``t``'s top 16 bits
    and moved up one when ``t`` reaches the next edge: ``estimate.weighted_radius``'s
    search, without a branch or a logarithm.
    """
    rows, n = t.shape
    bits = t.view(np.uint32)
    out = np.empty(rows, np.intp)
    hist = np.empty(RADIUS_BINS)
    for r in range(rows):
        hist[:] = 0.0
        for i in range(n):
            g = below[bits[r, i] >> 16]
            hist[g + (edges[g] <= t[r, i])] += w[r, i]
        total = 0.0
        for b in range(RADIUS_BINS):
            total += hist[b]
        target = q * total * (1.0 - 1e-12)
        cum = 0.0
        out[r] = 0
        for b in range(RADIUS_BINS):
            cum += hist[b]
            if cum >= target:
                out[r] = b
                break
    return out
