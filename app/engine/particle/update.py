"""Steps 1–11 for many filters of one floor at once, one numpy call per operation.

Randomness: every filter input carries its device's generator, and each
device draws its own blocks in a fixed order (its floors in index order,
then per phase), so a device's particles never depend on which other
devices share its batch.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from app.engine.particle import estimate, kernel, motion, weights
from app.engine.particle.bank import ParticleBank
from app.engine.particle.estimate import FilterEstimate
from app.engine.particle.floor_model import FloorModel, scatter
from app.engine.particle.inputs import FilterInput, readings_table
from app.engine.particle.motion import pull_towards_fixes
from app.engine.particle.mutation import mutate_and_centre
from app.engine.particle.params import ParticleFilterParams
from app.engine.particle.weights import alive_count, needs_resampling, reweight


@dataclass(frozen=True)
class _Loops:
    """The per-particle steps of one implementation, each with the numpy reference's signature."""

    move: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]]
    log_likelihood: Callable[..., np.ndarray]
    resample: Callable[..., None]
    estimate: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


_LOOPS = {
    "numpy": _Loops(
        motion.move_particles,
        weights.log_likelihood,
        weights.resample_rows,
        estimate.cloud_estimate,
    ),
    "numba": _Loops(
        kernel.move_particles, kernel.log_likelihood, kernel.resample_rows, kernel.cloud_estimate
    ),
}


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
            noise = draws.motion[i_m]
            if inp.walks:
                # a random walk's speed: see ``motion.walk_displacement``
                rng.standard_exponential(out=noise[0], dtype=np.float32)
                rng.random(out=noise[1], dtype=np.float32)
            else:
                rng.random(out=noise, dtype=np.float32)
            i_m += 1
        if mutate[r]:
            rng.random(out=draws.mutate[i_u])
            rng.standard_normal(out=draws.centre[i_u])
            i_u += 1
    return draws


def _select(mask: np.ndarray) -> slice | np.ndarray:
    """Return an index for the rows where ``mask`` holds: a slice (views) when it holds for all."""
    return slice(None) if mask.all() else np.flatnonzero(mask)


def _update_chunk(
    bank: ParticleBank,
    model: FloorModel,
    inputs: Sequence[FilterInput],
    p: ParticleFilterParams,
) -> list[FilterEstimate]:
    """Run steps 1–11 for at most ``p.chunk`` filters of one floor."""
    n = p.n_particles
    loops = _LOOPS[p.kernel]
    slots = np.array([i.slot for i in inputs], dtype=np.intp)
    t = np.array([i.t for i in inputs], dtype=np.int64)
    # consecutive slots are worked on in place, others copied out and back
    contiguous = bool(np.all(np.diff(slots) == 1))
    where = slice(int(slots[0]), int(slots[-1]) + 1) if contiguous else slots
    x, y, alpha, w = bank.x[where], bank.y[where], bank.alpha[where], bank.w[where]

    tx, rssi, count, valid = readings_table(model, inputs)
    radio = np.array([i.tx.size > 0 for i in inputs])

    # Decisions that depend only on the state before the move.
    stale = ~bank.sampled[slots] | (t - bank.last_radio[slots] > p.rescatter_after_ms)
    starving = ~stale & (alive_count(w, p.dead_weight) < p.min_alive)
    weigh = (t - bank.last_weights[slots] >= p.update_interval_ms) & valid.any(axis=1)
    mutate = weigh & (valid.sum(axis=1) >= p.min_transmitters)
    moving = np.array([not i.walks or i.walk_s > 0 for i in inputs])
    draws = _draw(inputs, stale | starving, moving, mutate, p)
    scatter_rows = np.cumsum(stale | starving) - 1

    # Step 1.
    rows = np.flatnonzero(stale)
    if rows.size:
        x[rows], y[rows], alpha[rows] = scatter(model, draws.scatter[scatter_rows[rows]])
        w[rows] = 1.0 / n

    # Step 2: motion, then the pull of positional measurements.
    if moving.any():
        sel = _select(moving)
        x[sel], y[sel], alpha[sel] = loops.move(
            model,
            x[sel],
            y[sel],
            alpha[sel],
            [i for i, m in zip(inputs, moving, strict=True) if m],
            draws.motion,
            p,
        )
    pulled = np.array([i.fix is not None for i in inputs])
    if pulled.any():
        rows = np.flatnonzero(pulled)
        fix = np.array([inputs[r].fix for r in rows.tolist()], dtype=np.float64)
        x[rows], y[rows] = pull_towards_fixes(
            model, x[rows], y[rows], fix, bank.radius[slots[rows]]
        )

    # Step 3.
    rows = np.flatnonzero(starving)
    if rows.size:
        x[rows], y[rows], alpha[rows] = scatter(model, draws.scatter[scatter_rows[rows]])
        w[rows] = 1.0 / n

    # Steps 5–9.
    if mutate.any():
        sel = _select(mutate)
        xr, yr, ar, wr = x[sel], y[sel], alpha[sel], w[sel]
        mutate_and_centre(
            model,
            xr,
            yr,
            ar,
            wr,
            tx[sel],
            rssi[sel],
            valid[sel],
            draws.mutate,
            draws.centre,
            p,
        )
        x[sel], y[sel], alpha[sel], w[sel] = xr, yr, ar, wr

    # Step 10.
    if weigh.any():
        sel = _select(weigh)
        ll = loops.log_likelihood(model, x[sel], y[sel], tx[sel], rssi[sel], count[sel], valid[sel])
        w[sel] = reweight(w[sel], ll)
        bank.last_weights[slots[sel]] = t[sel]
    bank.last_radio[slots[radio]] = t[radio]

    # Step 11: the device draws its uniform only when it resamples.
    resample = needs_resampling(w, p.resample_n)
    if resample.any():
        picked = np.flatnonzero(resample)
        u = np.array([inputs[r].rng.random() for r in picked.tolist()])
        loops.resample(x, y, alpha, w, picked, u)

    mx, my, heading, radius = loops.estimate(x, y, alpha, w)
    if not contiguous:
        bank.x[slots], bank.y[slots], bank.alpha[slots], bank.w[slots] = x, y, alpha, w
    bank.sampled[slots] = True
    bank.radius[slots] = radius
    return [
        FilterEstimate(float(mx[r]), float(my[r]), float(heading[r]), float(radius[r]), bool(s))
        for r, s in enumerate(resample)
    ]
