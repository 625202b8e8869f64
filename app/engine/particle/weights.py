"""Steps 3, 10 and 11: live particles, the readings' likelihood, resampling."""

from __future__ import annotations

import numpy as np

from app.engine.particle.floor_model import FloorModel
from app.engine.pathloss import grid_log_likelihood


def alive_count(w: np.ndarray, eps: float) -> np.ndarray:
    """Step 3: number of particles with weight above ε, per filter (D,)."""
    return np.count_nonzero(w > eps, axis=-1)


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

    The exponential is taken in float32, at a fraction of float64's cost: its
    relative error of 10⁻⁷ is nothing beside the weights' spread, and a
    particle over 87 nats below the best, whose likelihood then rounds to 0
    instead of below 10⁻³⁸, was dead either way.
    """
    lik = np.exp(ll - ll.max(axis=-1, keepdims=True))
    # w_i ← w_i p_i / Σ_j w_j p_j
    out = w * lik
    total = out.sum(axis=-1, keepdims=True)
    lost = total[:, 0] <= 1e-300
    if lost.any():
        out[lost] = lik[lost]
        total[lost] = lik[lost].sum(axis=-1, keepdims=True, dtype=np.float64)
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


def log_likelihood(
    model: FloorModel,
    x: np.ndarray,
    y: np.ndarray,
    tx: np.ndarray,
    rssi: np.ndarray,
    count: np.ndarray,
    valid: np.ndarray,
) -> np.ndarray:
    """Step 10: each particle's log-likelihood of its filter's readings, up to a row constant.

    A gather from the floor's expected-RSSI raster: Gaussian in each reading
    with its transmitter's σ, each transmitter weighted by its reading count.

    Parameters
    ----------
    x, y : ndarray of float32, shape (R, N)
        Particle positions (m).
    tx, rssi, count, valid : ndarray, shape (R, M)
        The readings table (``inputs.readings_table``) of the same rows.

    Returns
    -------
    ndarray, shape (R, N)
    """
    local, cw = reading_weights(model, tx, count, valid)
    return grid_log_likelihood(model.grid, model.grid.cell_index(x, y), local, rssi, cw)


def reading_weights(
    model: FloorModel, tx: np.ndarray, count: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Return each reading's raster column and weight n_m / (2 σ_m²) (0 for padding), (R, M)."""
    sigma = np.where(valid, model.sigma[tx], 1.0)
    # c_m = n_m / (2 σ_m²), zero for padding
    cw = np.where(valid, count / (2.0 * sigma * sigma), 0.0)
    return np.maximum(model.local[tx], 0), cw


def resample_rows(
    x: np.ndarray,
    y: np.ndarray,
    alpha: np.ndarray,
    w: np.ndarray,
    rows: np.ndarray,
    u: np.ndarray,
) -> None:
    """Step 11 in place on ``rows`` of (D, N) arrays: copies from each row's CDF, w = 1/N.

    ``u`` holds one uniform per resampled row (``resample_indices``).
    """
    n = w.shape[1]
    # copies of row r come from row r: flat index r·N + i
    flat = (resample_indices(w[rows], u) + rows[:, None] * n).ravel()
    x[rows] = x.ravel().take(flat).reshape(-1, n)
    y[rows] = y.ravel().take(flat).reshape(-1, n)
    alpha[rows] = alpha.ravel().take(flat).reshape(-1, n)
    w[rows] = 1.0 / n
