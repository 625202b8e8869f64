"""Step 2: particles move by the window's steps or a random walk, then towards fixes.

A window's steps (one or two at walking cadence, a nearly straight metre or
so) are summed into one move per particle and checked against the plan
once. Motion noise is uniform with the configured standard deviation:
numpy's Gaussian draws cost about four uniform ones, and the sum over
windows is Gaussian anyway. Without steps a particle walks at random, its
speed Rayleigh.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from app.engine.particle.floor_model import FloorModel
from app.engine.particle.inputs import FilterInput, steps_table
from app.engine.particle.params import ParticleFilterParams
from app.engine.particle.walls import moves_free

Moves = tuple[np.ndarray, np.ndarray, np.ndarray]
"""Each particle's move (dx, dy, m) and new direction (rad), float32 arrays of shape (R, N)."""


def error_scales(params: ParticleFilterParams) -> tuple[np.float32, np.float32]:
    """Return √3 σ_L (m) and √3 σ_θ (rad) in float32, the scales of the motion errors.

    A uniform on [-√3 σ, √3 σ) has standard deviation σ, so (2u - 1) √3 σ
    draws a step's length or heading error.
    """
    root3 = np.float32(np.sqrt(3.0))
    return (
        root3 * np.float32(params.step_length_std_m),
        root3 * np.float32(np.radians(params.heading_std_deg)),
    )


def heading_sums(
    length: np.ndarray, heading: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return a window's V = Σ L_j u_j and U = Σ u_j, u_j = (sin θ_j, cos θ_j), and θ_last.

    For rows whose every step has a heading; each a float32 column, shape (R, 1).
    """
    real = length > 0
    sin_h, cos_h = np.sin(heading) * real, np.cos(heading) * real
    vx = np.sum(length * sin_h, axis=1, keepdims=True).astype(np.float32)
    vy = np.sum(length * cos_h, axis=1, keepdims=True).astype(np.float32)
    ux = np.sum(sin_h, axis=1, keepdims=True).astype(np.float32)
    uy = np.sum(cos_h, axis=1, keepdims=True).astype(np.float32)
    return vx, vy, ux, uy, heading[:, -1:].astype(np.float32)


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
    length_scale, heading_scale = error_scales(params)
    e_len = (2.0 * noise[0] - 1.0) * length_scale
    e_dir = (2.0 * noise[1] - 1.0) * heading_scale
    known = ~np.isnan(heading).any(axis=1)
    dx = np.empty(alpha.shape, np.float32)
    dy = np.empty(alpha.shape, np.float32)
    direction = np.empty(alpha.shape, np.float32)
    if known.any():
        # every row, as a phone's windows mostly are: views, no row copies
        rows = slice(None) if known.all() else np.flatnonzero(known)
        vx, vy, ux, uy, last = heading_sums(length[rows], heading[rows])
        el, ed = e_len[rows], e_dir[rows]
        s, c = np.sin(ed), np.cos(ed)
        # (a, b) = V + ε_L U, rotated clockwise by ε_θ
        a = vx + el * ux
        b = vy + el * uy
        dx[rows] = a * c + b * s
        dy[rows] = b * c - a * s
        direction[rows] = last + ed
    if not known.all():
        rows = np.flatnonzero(~known)
        real = length[rows] > 0
        k = real.sum(axis=1, keepdims=True).astype(np.float32)
        total = length[rows].sum(axis=1, keepdims=True).astype(np.float32)
        free_dir = alpha[rows] + e_dir[rows]
        # along α: ℓ = Σ L_j + k ε_L
        ell = np.maximum(total + k * e_len[rows], 0.0)
        dx[rows] = ell * np.sin(free_dir)
        dy[rows] = ell * np.cos(free_dir)
        direction[rows] = free_dir
    return dx, dy, direction


def walk_scales(
    dt_s: np.ndarray, params: ParticleFilterParams
) -> tuple[np.ndarray, np.ndarray, np.float32]:
    """Return the scales of a random walk's draws, in float32.

    Δt (s) and the turn's √3 σ_turn √Δt (rad), columns of shape (D, 1), and
    the speed prior's σ_v (m/s).
    """
    dt = np.asarray(dt_s, dtype=np.float32)
    root3 = np.float32(np.sqrt(3.0))
    turn_sd = np.float32(np.radians(params.walk_turn_std_deg))
    return dt, root3 * turn_sd * np.sqrt(dt), np.float32(params.walk_speed_mps)


def walk_displacement(
    dt_s: np.ndarray, alpha: np.ndarray, noise: np.ndarray, params: ParticleFilterParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2 without an inertial stream: a correlated random walk with a speed prior.

    The speed prior is Rayleigh with scale σ_v, the speed of a velocity whose
    components are independent N(0, σ_v²): σ_v √(2E) with E a standard
    exponential, which numpy draws by its ziggurat, without the logarithm
    that inverting the Rayleigh CDF costs for every particle.

    Parameters
    ----------
    dt_s : ndarray, shape (D, 1)
        Time since the previous update (s).
    alpha : ndarray of float32, shape (D, N)
        Current particle directions (rad).
    noise : ndarray of float32, shape (2, D, N)
        Standard exponentials for the speed, uniforms in [0, 1) for the turn.

    Returns
    -------
    dx, dy, direction : ndarray of float32, shape (D, N)
    """
    dt, turn_scale, speed_scale = walk_scales(dt_s, params)
    # turn ~ uniform with σ = σ_turn √Δt
    direction = alpha + (2.0 * noise[1] - 1.0) * turn_scale
    # |v| = σ_v √(2 E), Δ = |v| Δt (sin α, cos α)
    speed = speed_scale * np.sqrt(np.float32(2.0) * noise[0])
    step = speed * dt
    return step * np.sin(direction), step * np.cos(direction), direction


def displacements(
    alpha: np.ndarray,
    inputs: list[FilterInput],
    noise: np.ndarray,
    p: ParticleFilterParams,
    walk: Callable[..., Moves] = walk_displacement,
    window: Callable[..., Moves] = window_displacement,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 2 for moving filters: each particle's intended move and direction.

    Parameters
    ----------
    alpha : ndarray of float32, shape (R, N)
        Current particle directions (rad).
    noise : ndarray of float32, shape (R, 2, N)
        The rows' motion draws: uniforms, but for the speed of a row without
        steps, which is a standard exponential (``walk_displacement``).

    Returns
    -------
    dx, dy, direction : ndarray of float32, shape (R, N)
        Moves (m) and directions (rad) of the particles that make their move.
    long : ndarray of bool, shape (R,)
        Rows whose moves may exceed ``max_move_m`` (random walks, windows of
        many steps) and must be shortened to it.

    ``walk`` and ``window`` move the rows of each kind, with the signatures of
    ``walk_displacement`` and ``window_displacement`` (the compiled kernel
    passes its own).
    """
    noise_t = noise.transpose(1, 0, 2)
    walking = np.array([i.walks for i in inputs])
    long = _long_rows(inputs, p)
    if walking.all() or not walking.any():
        # one kind of motion (a site's tags, or its phones): views, no row copies
        walks = bool(walking.all())
        kind = walk if walks else window
        return (*_rows_displacement(inputs, kind, walks, alpha, noise_t, p), long)
    dx = np.empty(alpha.shape, np.float32)
    dy = np.empty(alpha.shape, np.float32)
    direction = np.empty(alpha.shape, np.float32)
    for rows, kind, walks in (
        (np.flatnonzero(~walking), window, False),
        (np.flatnonzero(walking), walk, True),
    ):
        chosen = [inputs[r] for r in rows]
        out = _rows_displacement(chosen, kind, walks, alpha[rows], noise_t[:, rows], p)
        dx[rows], dy[rows], direction[rows] = out
    return dx, dy, direction, long


def _long_rows(inputs: list[FilterInput], p: ParticleFilterParams) -> np.ndarray:
    """Return which rows' moves may exceed ``max_move_m`` and must be shortened to it.

    Random walks, and windows of so many steps that their length with the
    largest errors (√3 σ_L a step) exceeds it.
    """
    error = np.sqrt(3.0) * p.step_length_std_m
    longest = np.array(
        [0.0 if i.walks else i.step_length.sum() + i.step_length.size * error for i in inputs]
    )
    return np.array([i.walks for i in inputs]) | (longest > p.max_move_m)


def _rows_displacement(
    inputs: list[FilterInput],
    move: Callable[..., Moves],
    walks: bool,
    alpha: np.ndarray,
    noise: np.ndarray,
    p: ParticleFilterParams,
) -> Moves:
    """Step 2 for rows that all walk at random or all take steps: moves and directions."""
    if walks:
        return move(np.array([[i.walk_s] for i in inputs]), alpha, noise, p)
    length, heading = steps_table(inputs)
    return move(length, heading, alpha, noise, p)


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
    """Step 2: make the moves the plan allows; a blocked particle stays put and turns at random.

    Moves of ``long`` rows are first shortened to ``max_move_m``. A blocked
    particle takes the direction (2u - 1) π from ``turn``, the uniform that
    drew its heading error: that draw only shaped the move it did not make,
    so it is still an independent uniform.

    Parameters
    ----------
    x, y, dx, dy, direction, turn : ndarray of float32, shape (R, N)
    long : ndarray of bool, shape (R,)

    Returns
    -------
    x, y, alpha : ndarray of float32, shape (R, N)
    """
    rows = np.flatnonzero(long)
    if rows.size:
        norm = np.hypot(dx[rows], dy[rows])
        scale = np.minimum(1.0, np.float32(max_move_m) / np.maximum(norm, 1e-6))
        dx[rows] *= scale
        dy[rows] *= scale
    nx, ny = x + dx, y + dy
    ok = moves_free(model.walls, x, y, nx, ny)
    # α = θ for a made move, (2u - 1) π for a blocked one
    alpha = np.where(ok, direction, (2.0 * turn - 1.0) * np.float32(np.pi))
    return np.where(ok, nx, x), np.where(ok, ny, y), alpha


def move_particles(
    model: FloorModel,
    x: np.ndarray,
    y: np.ndarray,
    alpha: np.ndarray,
    inputs: list[FilterInput],
    noise: np.ndarray,
    p: ParticleFilterParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2 for moving filters: the window's move of every particle, checked against the plan."""
    dx, dy, direction, long = displacements(alpha, inputs, noise, p)
    return settle_moves(model, x, y, dx, dy, direction, noise[:, 1], long, p.max_move_m)


def pull_towards_fixes(
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
    k = np.divide(r_pf, r_pf + fix[:, 2], out=np.ones(r_pf.shape), where=np.isfinite(r_pf))
    k = k[:, None]
    px = x + k * (fxy[:, :1] - x)
    py = y + k * (fxy[:, 1:] - y)
    ok = model.plan.is_free(np.stack([px, py], axis=-1))
    return np.where(ok, px, x), np.where(ok, py, y)
