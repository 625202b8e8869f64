"""The HMM's transition (step 2 in ``app.engine.hmm``): PDR steps as a kernel on the grid."""

from __future__ import annotations

import math

import numpy as np

from app.engine.hmm.kernels import gaussian_kernel


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
    return gaussian_kernel(
        float(d[0]), float(d[1]), cov[0, 0], cov[0, 1], cov[1, 1], cell, n_sigmas
    )
