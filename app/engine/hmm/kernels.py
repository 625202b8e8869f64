"""The HMM's per-scan loops, compiled.

The pooled emission with its floor marginals, the transition's Gaussian and
its spread over occupied cells, and the k-NN fix's mixture density. Each
replaces a chain of numpy calls on arrays of a few thousand points, where the
calls' own overhead and the temporaries cost more than the arithmetic. Compiled once per process
(numba's disk cache); ``load_kernels`` does it before a device needs them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def pooled_emission(
    d: np.ndarray,
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    scan_indptr: np.ndarray,
    scan_points: np.ndarray,
    point_start: np.ndarray,
    surveyed: np.ndarray,
    pool_db: float,
    max_db: float,
    nats: float,
    rescale: float,
    cap_margin_db: float,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Return every point's log-likelihood of a scan and each floor's log marginal.

    ``d`` are the scan's distances to every survey scan. A point pools the
    survey scans around it (row j of the CSR ``indptr, indices, data``; the
    points pooling scan s are ``scan_points[scan_indptr[s]:scan_indptr[s+1]]``;
    floor f's points at ``point_start[f]:point_start[f+1]``, its first
    ``surveyed[f]`` its own): ``ln L_j = -nats · min(-pool_db ln Σ_s K_js e_s,
    max_db)`` with ``e_s = exp(-(d_s - d_min) / pool_db)``. The marginal is
    ``ln mean_j exp(rescale · ln L_j)`` over a floor's own points.

    A point whose every scan is ``max_db`` past the best is capped, whatever
    its sum (its rows' weights sum to at most 1): only points pooling a scan
    within ``max_db`` of the best are summed, a few percent of a building's.
    """
    best = np.inf
    for s in range(d.size):
        best = min(best, d[s])
    n_points = point_start[point_start.size - 1]
    touched = np.zeros(n_points, dtype=np.bool_)
    for s in range(d.size):
        if d[s] < best + max_db + cap_margin_db:
            for k in range(scan_indptr[s], scan_indptr[s + 1]):
                touched[scan_points[k]] = True
    capped = -nats * max_db
    ll = np.full(n_points, capped)
    e = np.full(d.size, -1.0)
    for j in range(n_points):
        if not touched[j]:
            continue
        pooled = 0.0
        for k in range(indptr[j], indptr[j + 1]):
            s = indices[k]
            if e[s] < 0.0:
                e[s] = math.exp(-(d[s] - best) / pool_db)
            pooled += data[k] * e[s]
        ll[j] = -nats * min(-pool_db * math.log(max(pooled, 1e-300)), max_db)
    n_floors = point_start.size - 1
    marginal = np.empty(n_floors)
    for f in range(n_floors):
        lo, own = point_start[f], surveyed[f]
        if own == 0:
            marginal[f] = -np.inf
            continue
        top = -np.inf
        for j in range(lo, lo + own):
            top = max(top, rescale * ll[j])
        total = 0.0
        n_capped = 0
        for j in range(lo, lo + own):
            if touched[j]:
                total += math.exp(rescale * ll[j] - top)
            else:
                n_capped += 1
        total += n_capped * math.exp(rescale * capped - top)
        marginal[f] = top + math.log(total) - math.log(own)
    return ll, marginal


@njit(cache=True)
def propagate(
    prob: np.ndarray, ij: np.ndarray, grid: np.ndarray, kernel: np.ndarray, h: int
) -> np.ndarray:  # pragma: no cover - compiled
    """Move a distribution over reference points by a transition kernel.

    Each point with probability spreads it over the cells within ``h`` of
    its own, ``kernel[h + dr, h + dc]`` to the cell ``dr`` rows and ``dc``
    columns away; mass landing on cells that are not reference points is
    lost. A direct sum: a device's posterior holds a few hundred points and
    the kernel a few hundred cells.

    Parameters
    ----------
    prob : ndarray, shape (P,)
        Probability of each reference point.
    ij : ndarray of int, shape (P, 2)
        Grid row and column of each point.
    grid : ndarray of int, shape (ny, nx)
        Point index of each grid cell, -1 where none.
    kernel : ndarray, shape (2h + 1, 2h + 1)
        From ``transition_kernel``.
    h : int
        Kernel half-width (cells).

    Returns
    -------
    ndarray, shape (P,)
        Σ_i p_i K(x_j - x_i) at every point j (not renormalised).
    """
    ny, nx = grid.shape
    out = np.zeros(prob.size)
    for i in range(prob.size):
        p = prob[i]
        if p <= 0.0:
            continue
        r, c = ij[i, 0], ij[i, 1]
        for dr in range(max(-h, -r), min(h, ny - 1 - r) + 1):
            for dc in range(max(-h, -c), min(h, nx - 1 - c) + 1):
                j = grid[r + dr, c + dc]
                if j >= 0:
                    out[j] += p * kernel[h + dr, h + dc]
    return out


@njit(cache=True)
def gaussian_kernel(
    dx: float, dy: float, cxx: float, cxy: float, cyy: float, cell: float, n_sigmas: float
) -> tuple[np.ndarray, int]:  # pragma: no cover - compiled
    """Return a displacement's Gaussian on the grid, normalised, and its half-width (cells).

    ``kernel[h + r, h + c]`` is the probability of moving ``c`` columns (x) and
    ``r`` rows (y); the mean is (dx, dy) m and the covariance [[cxx, cxy],
    [cxy, cyy]] m². It reaches ``n_sigmas`` standard deviations of the widest
    axis past the mean. The 2 × 2 eigenvalue and inverse are closed forms.
    """
    # λ_max = (a + c) / 2 + sqrt(((a - c) / 2)² + b²)
    half = 0.5 * (cxx - cyy)
    widest = 0.5 * (cxx + cyy) + math.sqrt(half * half + cxy * cxy)
    reach = math.hypot(dx, dy) + n_sigmas * math.sqrt(widest)
    h = int(math.ceil(reach / cell))
    det = cxx * cyy - cxy * cxy
    ixx, ixy, iyy = cyy / det, -cxy / det, cxx / det
    size = 2 * h + 1
    kernel = np.empty((size, size))
    total = 0.0
    for r in range(size):
        oy = (r - h) * cell - dy
        for c in range(size):
            ox = (c - h) * cell - dx
            # K ∝ exp(-½ (o - D)ᵀ Σ⁻¹ (o - D))
            value = math.exp(-0.5 * (ixx * ox * ox + 2.0 * ixy * ox * oy + iyy * oy * oy))
            kernel[r, c] = value
            total += value
    for r in range(size):
        for c in range(size):
            kernel[r, c] /= total
    return kernel, h


@njit(cache=True)
def mixture_log_density(
    xy: np.ndarray, centres: np.ndarray, weight: np.ndarray, sigma: float, floor_nats: float
) -> np.ndarray:  # pragma: no cover - compiled
    """Return ln Σ_i w_i exp(-|x - c_i|² / 2σ²) at each of ``xy`` (n, 2).

    Relative to its largest value at a centre, and at least ``-floor_nats``.
    """
    k = centres.shape[0]
    scale = -0.5 / (sigma * sigma)
    peak = 0.0
    for a in range(k):
        at = 0.0
        for b in range(k):
            dx, dy = centres[a, 0] - centres[b, 0], centres[a, 1] - centres[b, 1]
            at += weight[b] * math.exp(scale * (dx * dx + dy * dy))
        peak = max(peak, at)
    log_peak = math.log(peak)
    out = np.empty(xy.shape[0])
    for j in range(xy.shape[0]):
        density = 0.0
        for b in range(k):
            dx, dy = xy[j, 0] - centres[b, 0], xy[j, 1] - centres[b, 1]
            density += weight[b] * math.exp(scale * (dx * dx + dy * dy))
        out[j] = max(math.log(max(density, 1e-300)) - log_peak, -floor_nats)
    return out


def load_kernels() -> None:
    """Run each kernel once on a tiny input, so it is compiled before a device needs it.

    The first call in a process compiles it, or reads it from numba's disk cache.
    """
    one = np.zeros(1)
    starts = np.array([0, 1], dtype=np.int64)
    index = np.zeros(1, dtype=np.int32)
    pooled_emission(
        one, starts, index, np.ones(1), starts, index, starts, np.ones(1, dtype=np.int64),
        3.0, 30.0, 0.5, 2.0, 1e-6,
    )  # fmt: skip
    cells = np.zeros((1, 2), dtype=np.int32)
    propagate(np.ones(1), cells, np.zeros((1, 1), dtype=np.int32), np.ones((1, 1)), 0)
    gaussian_kernel(0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 3.0)
    mixture_log_density(np.zeros((1, 2)), np.zeros((1, 2)), np.ones(1), 1.0, 30.0)
