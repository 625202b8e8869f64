"""Steps 7–9: particles placed afresh, at random and around the nearest transmitter.

Mutation (step 7) keeps the cloud from collapsing onto a wrong mode; centre
sampling (steps 8–9) puts a few particles near the heard transmitter nearest
by the inverse path loss, Gaussian as the patent says.
"""

from __future__ import annotations

import numpy as np

from app.engine.particle.floor_model import FloorModel, scatter
from app.engine.particle.params import ParticleFilterParams
from app.engine.pathloss import range_from_rssi


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


def mutate_and_centre(
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
    """Run steps 7–9 in place on rows of (R, N) arrays; new particles get w = 1/N.

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
