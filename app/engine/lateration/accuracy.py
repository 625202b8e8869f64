"""Grinyak's (2020) measurement model, and the checks that give a fix's accuracy in advance.

The readings are ranges ``h = d`` (UWB) or path loss ``h = A - B ln d`` (RSSI):
the paper's ``u = u* - 10 n log10(d / d*)`` with ``d* = 1 m``, ``A = u*`` and
``B = 10 n / ln 10``. Linearised around a position, with H the Jacobian and Q
the readings' covariance, three checks decide whether a fix can be trusted:
the rank of H (observability: all emitters and the object in one plane make
the height unobservable), its condition number (stability, μ < μ*) and
``D = (Hᵀ Q⁻¹ H)⁻¹`` (accuracy). None of them needs a measurement, which is
how ``accuracy_map`` predicts the error of a layout. With M readings of one
emitter the mean reading has variance σ²/M, which is how repeated readings
enter Q.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

Model = Literal["range", "rssi"]


def path_loss_B(n: float) -> float:
    """Return B of ``rssi = A - B ln r`` for the paper's exponent n (B = 10 n / ln 10)."""
    # B = 10 n / ln 10
    return 10.0 * n / np.log(10.0)


def predict(
    model: Model,
    points: np.ndarray,
    emitters: np.ndarray,
    A: np.ndarray | None = None,
    B: np.ndarray | None = None,
    min_distance: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Return predicted readings and their Jacobian with respect to the position.

    Parameters
    ----------
    model : {"range", "rssi"}
        ``range``: h = d (m); ``rssi``: h = A - B ln d (dBm).
    points : ndarray, shape (N, 3)
        Object positions (m).
    emitters : ndarray, shape (K, 3)
        Anchor or transmitter positions (m).
    A, B : ndarray, shape (K,), optional
        Path-loss parameters (dBm, dB per ln m); needed for ``rssi``.
    min_distance : float
        Floor on distances (m).

    Returns
    -------
    h : ndarray, shape (N, K)
    J : ndarray, shape (N, K, 3)
        ∂h/∂(x, y, z).
    """
    diff = points[:, None, :] - emitters[None, :, :]
    # d = |p − e|, floored
    d = np.maximum(np.linalg.norm(diff, axis=-1), min_distance)
    if model == "range":
        # ∂d/∂p = (p − e) / d
        return d, diff / d[..., None]
    if A is None or B is None:
        raise ValueError("the rssi model needs A and B")
    # h = A − B ln d
    h = A[None, :] - B[None, :] * np.log(d)
    # ∂h/∂p = −B (p − e) / d²  (Grinyak 2020, eq. 3 with B = 10 n / ln 10)
    return h, -B[None, :, None] * diff / (d * d)[..., None]


def whitened_jacobian(
    model: Model,
    points: np.ndarray,
    emitters: np.ndarray,
    std: np.ndarray,
    dims: int = 3,
    B: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    min_distance: float = 0.01,
) -> np.ndarray:
    """Return √W Q^(−½) H of a fix at each point, whose checks give the a-priori accuracy.

    Parameters
    ----------
    model : {"range", "rssi"}
    points : ndarray, shape (N, 3)
    emitters : ndarray, shape (K, 3)
    std : ndarray, shape (K,) or (N, K)
        Standard deviation of each (averaged) reading: m for ranges, dB for
        RSSI (σ/√M for a mean of M readings); NaN or ∞ where not heard.
    dims : {2, 3}
        2: derivatives in x, y only (height known); 3: x, y, z.
    B : ndarray, shape (K,), optional
        Path-loss slope, needed for ``rssi`` (A does not enter H).
    weights : ndarray, shape (N, K), optional
        Robust weights; 1 when omitted.
    min_distance : float
        Floor on distances (m).

    Returns
    -------
    ndarray, shape (N, K, dims)
        Rows of readings not heard are zero.
    """
    K = emitters.shape[0]
    A = np.zeros(K) if model == "rssi" else None
    _, J = predict(model, points, emitters, A, B, min_distance)
    std = np.broadcast_to(np.asarray(std, dtype=float), (points.shape[0], K))
    heard = np.isfinite(std) & (std > 0)
    # row scale √w / σ, 0 where not heard
    scale = np.where(heard, 1.0 / np.where(heard, std, 1.0), 0.0)
    if weights is not None:
        scale = scale * np.sqrt(weights)
    return J[..., :dims] * scale[..., None]


def rank_tolerance(n_rows: int, n_cols: int) -> float:
    """Return the relative singular-value cut-off of numerical rank: max(rows, cols) · ε."""
    return max(n_rows, n_cols) * float(np.finfo(float).eps)


def covariance_checks(Hw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (D, cond, rank) of whitened Jacobians ``Hw`` = √W Q^(−½) H, shape (N, K, d).

    D = (Hwᵀ Hw)⁻¹ (N, d, d) is NaN where Hw is rank deficient; cond (N,) is
    s_max / s_min (∞ when rank deficient); rank (N,) is the numerical rank
    (singular values above :func:`rank_tolerance` times the largest).
    """
    _, s, vt = np.linalg.svd(Hw, full_matrices=False)
    tol = rank_tolerance(Hw.shape[-2], Hw.shape[-1]) * np.maximum(s[..., :1], 1e-300)
    rank = np.sum(s > tol, axis=-1)
    full = rank == Hw.shape[-1]
    s_safe = np.where(full[..., None], s, 1.0)
    with np.errstate(divide="ignore"):
        # μ = s_max / s_min
        cond = np.where(full, s[..., 0] / s_safe[..., -1], np.inf)
    # D = V S⁻² Vᵀ
    cov = np.einsum("nji,nj,njk->nik", vt, 1.0 / s_safe**2, vt)
    return np.where(full[:, None, None], cov, np.nan), cond, rank


def critical_condition(n_unknowns: int, eps: float = float(np.finfo(float).eps)) -> float:
    """Return the paper's critical condition number μ* for ``n_unknowns`` unknowns.

    μ* = 1 / ([√u (2u - 3)(4u + 27) + 11] ε₁) (Grinyak 2020, after Kryzhko &
    Glushakova): about 2·10¹³ for u = 3 in double precision.
    """
    u = float(n_unknowns)
    # μ* = 1 / ((√u (2u − 3)(4u + 27) + 11) ε)
    return 1.0 / ((np.sqrt(u) * (2 * u - 3) * (4 * u + 27) + 11.0) * eps)
