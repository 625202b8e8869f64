"""The HMM's transition (step 2 in ``app.engine.hmm``): PDR steps as a kernel on the grid."""

from __future__ import annotations

import math

import numpy as np
from scipy import signal


def step_displacement(
    length: float, heading_deg: float, length_std: float, heading_std_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Return one step's displacement (2,) and its covariance (2, 2).

    Scalar arithmetic: the tracker moves by every step as it comes, and
    array operations on one step cost more in numpy's overhead than in work.

    Parameters
    ----------
    length : float
        Step length (m).
    heading_deg : float
        Heading (degrees clockwise from +y); NaN moves nothing and spreads
        the step's length isotropically.
    length_std, heading_std_deg : float
        σ_d (m) and σ_φ (degrees) of the step.
    """
    if not math.isfinite(heading_deg):
        # unknown heading: the step may go anywhere within its length
        spread = (length**2 + length_std**2) / 2.0
        return np.zeros(2), np.array([[spread, 0.0], [0.0, spread]])
    psi = math.radians(heading_deg)
    # u = (sin ψ, cos ψ) along the step, n = (cos ψ, -sin ψ) across it
    ux, uy = math.sin(psi), math.cos(psi)
    along = length_std**2
    # across-track variance (L σ_φ)²
    across = (length * math.radians(heading_std_deg)) ** 2
    # Σ = σ_d² u uᵀ + (L σ_φ)² n nᵀ
    xx = along * ux * ux + across * uy * uy
    xy = along * ux * uy - across * uy * ux
    yy = along * uy * uy + across * ux * ux
    return np.array([length * ux, length * uy]), np.array([[xx, xy], [xy, yy]])


def transition_kernel(
    d: np.ndarray, cov: np.ndarray, cell: float, n_sigmas: float
) -> tuple[np.ndarray, int]:
    """Return the Gaussian transition kernel on the grid and its half-width (cells).

    ``kernel[h + dr, h + dc]`` is the probability of moving by ``dc`` columns
    (x) and ``dr`` rows (y); it is normalised to sum to 1.

    Parameters
    ----------
    d : ndarray, shape (2,)
        Mean displacement (m).
    cov : ndarray, shape (2, 2)
        Its covariance (m²), including the grid's quantisation.
    cell : float
        Grid cell (m).
    n_sigmas : float
        Truncation radius in standard deviations of the widest axis.
    """
    reach = float(np.hypot(*d) + n_sigmas * np.sqrt(np.linalg.eigvalsh(cov)[-1]))
    h = int(np.ceil(reach / cell))
    off = np.arange(-h, h + 1) * cell
    dx = off[None, :] - d[0]
    dy = off[:, None] - d[1]
    inv = np.linalg.inv(cov)
    # K ∝ exp(-½ (o - D)ᵀ Σ⁻¹ (o - D))
    q = inv[0, 0] * dx * dx + 2.0 * inv[0, 1] * dx * dy + inv[1, 1] * dy * dy
    kernel = np.exp(-0.5 * q)
    return kernel / kernel.sum(), h


def propagate(
    prob: np.ndarray, ij: np.ndarray, grid: np.ndarray, kernel: np.ndarray, h: int
) -> np.ndarray:
    """Move a distribution over reference points by a transition kernel.

    Only the bounding box of the points with non-zero probability is
    convolved; mass landing on cells that are not reference points is lost.

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
    active = np.flatnonzero(prob > 0)
    out = np.zeros_like(prob)
    if active.size == 0:
        return out
    r0, c0 = ij[active].min(axis=0)
    r1, c1 = ij[active].max(axis=0)
    image = np.zeros((r1 - r0 + 1, c1 - c0 + 1))
    image[ij[active, 0] - r0, ij[active, 1] - c0] = prob[active]
    # (p * K)[y] = Σ_x p[x] K[y - x]
    # FFT: scipy's automatic choice picks it here too, after 30 µs of deciding
    moved = signal.fftconvolve(image, kernel, mode="full")
    ny, nx = grid.shape
    lo_r, lo_c = r0 - h, c0 - h
    rr0, cc0 = max(lo_r, 0), max(lo_c, 0)
    rr1, cc1 = min(r1 + h, ny - 1), min(c1 + h, nx - 1)
    sub = grid[rr0 : rr1 + 1, cc0 : cc1 + 1]
    rows, cols = np.nonzero(sub >= 0)
    out[sub[rows, cols]] = moved[rows + rr0 - lo_r, cols + cc0 - lo_c]
    return out
