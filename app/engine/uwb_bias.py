"""Range biases of UWB anchor–tag pairs: self-calibration from redundancy, or from a survey.

Two-way ranges come out long by 10–30 cm, differently per anchor and tag
(antenna delays, the first path arriving through a body or furniture). A
constant offset per pair is removable two ways:

* **Self-calibration** (no truth needed). With more anchors than unknowns
  the residuals of a least-squares fix keep the part of the bias vector b
  that no position shift explains: ``r_k = (I − P_k) b + noise``, with P_k
  the orthogonal projector on the column space of that epoch's H. Stacking
  epochs gives the normal equations ``(Σ_k (I − P_k)) b = Σ_k r_k``: the
  positions eliminated, b alone remains, solvable once the tag has been seen
  from varied enough geometry for ``Σ (I − P_k)`` to be regular. On the
  trolley recording the two weakest directions (those that look like a
  shift of the tag) have eigenvalues well below the mean but far from zero,
  the others near it: well conditioned. The common-mode part (all ranges long) is never
  mistaken for a shift when anchors surround the tag. Fixes are computed
  from ranges already corrected by the current estimate b̂, so each epoch
  adds ``r_k + (I − P_k) b̂`` (its residual as if uncorrected). Sums forget
  with a time constant, and a weak prior (zero, or a survey) keeps anchors
  never seen at their prior.
  A running mean of the residuals alone (gain 1/n) would have the same
  fixed point but converges like n^(−λ) with λ the weak directions'
  eigenvalue: on the recording it was still drifting minutes in.
* **Survey calibration**: ranges recorded at known positions give the bias
  directly as the median of measured minus true range per pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BiasParams:
    """Tuning of the self-calibration.

    Attributes
    ----------
    time_constant_s : float
        Accumulated equations decay as exp(−Δt / τ): a bias that changes
        (temperature, a moved anchor) is followed within a few τ.
    prior_weight : float
        Weight of the prior bias (0, or a survey) in units of one epoch's
        equation: it only matters until a few epochs have been seen.
    min_readings : int
        Fixes with fewer inlier readings are skipped: with the unknowns of a
        2-D fix (2) plus 2 there is some redundancy to learn from.
    min_weight : float
        Readings whose robust weight fell below this are outliers (NLOS)
        and teach nothing about the constant bias.
    max_abs_m : float
        Bias estimates are clipped to ±this (m).
    """

    time_constant_s: float = 300.0
    prior_weight: float = 10.0
    min_readings: int = 4
    min_weight: float = 0.5
    max_abs_m: float = 1.0


@dataclass(frozen=True)
class SurveyBiases:
    """Biases measured at known positions, per anchor (K,): median, robust spread, count.

    ``bias`` and ``spread`` (1.4826 × median absolute deviation) are in m,
    NaN for anchors never heard during the survey.
    """

    bias: np.ndarray
    spread: np.ndarray
    count: np.ndarray


def residual_projector(anchors_xyz: np.ndarray, position: np.ndarray, dims: int) -> np.ndarray:
    """Return I − P for a fix at ``position`` from ``anchors_xyz`` (K, 3), shape (K, K).

    P = H (Hᵀ H)⁻¹ Hᵀ projects on the directions a change of the ``dims``
    solved coordinates can explain; H holds the unit vectors (p − a)/|p − a|.
    """
    diff = position[None, :] - anchors_xyz
    H = (diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-9)[:, None])[:, :dims]
    # P = H H⁺
    P = H @ np.linalg.pinv(H)
    return np.eye(anchors_xyz.shape[0]) - P


def accumulate(
    S: np.ndarray,
    g: np.ndarray,
    bias: np.ndarray,
    anchors: np.ndarray,
    anchors_xyz: np.ndarray,
    position: np.ndarray,
    residuals: np.ndarray,
    weights: np.ndarray,
    decay: float,
    dims: int,
    params: BiasParams = BiasParams(),
) -> tuple[np.ndarray, np.ndarray]:
    """Fold one fix into the bias normal equations ``S b = g``.

    Parameters
    ----------
    S : ndarray, shape (M, M)
        Accumulated Σ (I − P_k) over all M anchors of the site.
    g : ndarray, shape (M,)
        Accumulated residuals as if uncorrected (m).
    bias : ndarray, shape (M,)
        The estimate the fix's ranges were corrected with (m).
    anchors : ndarray of int, shape (K,)
        Anchor index of each reading of the fix.
    anchors_xyz : ndarray, shape (M, 3)
        Anchor positions (m).
    position : ndarray, shape (3,)
        The fix (m).
    residuals : ndarray, shape (K,)
        Corrected range minus predicted range at the fix (m); NaN where unused.
    weights : ndarray, shape (K,)
        Robust weights of the fix.
    decay : float
        Factor the old sums are multiplied by first, exp(−Δt / τ).
    dims : int
        Coordinates the fix solved (2 or 3).
    params : BiasParams

    Returns
    -------
    S, g : ndarray
        Updated copies (unchanged but decayed when the fix is skipped).
    """
    S = np.array(S, dtype=float) * decay
    g = np.array(g, dtype=float) * decay
    inlier = np.isfinite(residuals) & (weights >= params.min_weight)
    if inlier.sum() < params.min_readings:
        return S, g
    k = np.asarray(anchors)[inlier]
    M = residual_projector(anchors_xyz[k], position, dims)
    # S += I − P_k
    S[np.ix_(k, k)] += M
    # g += r_k + (I − P_k) b̂
    g[k] += residuals[inlier] + M @ bias[k]
    return S, g


def solve_biases(
    S: np.ndarray, g: np.ndarray, prior: np.ndarray, params: BiasParams = BiasParams()
) -> np.ndarray:
    """Return b̂ = (S + λI)⁻¹ (g + λ b₀), the biases (m) with prior b₀ of weight λ, clipped."""
    lam = params.prior_weight
    A = S + lam * np.eye(S.shape[0])
    # b̂ = (S + λI)⁻¹ (g + λ b₀)
    b = np.linalg.solve(A, g + lam * prior)
    return np.clip(b, -params.max_abs_m, params.max_abs_m)


def survey_biases(anchors_xyz: np.ndarray, ranges: np.ndarray, truth: np.ndarray) -> SurveyBiases:
    """Measure per-anchor biases from ranges taken at known positions.

    Parameters
    ----------
    anchors_xyz : ndarray, shape (K, 3)
        Anchor positions (m).
    ranges : ndarray, shape (N, K)
        Measured ranges (m), NaN where missing.
    truth : ndarray, shape (N, 3)
        The tag's true positions (m) at the same instants.

    Returns
    -------
    SurveyBiases
    """
    # e = r − |p − a|
    err = ranges - np.linalg.norm(truth[:, None, :] - anchors_xyz[None, :, :], axis=-1)
    count = np.isfinite(err).sum(axis=0)
    heard = count > 0
    bias = np.full(err.shape[1], np.nan)
    spread = np.full(err.shape[1], np.nan)
    bias[heard] = np.nanmedian(err[:, heard], axis=0)
    # σ ≈ 1.4826 · median |e − median e|
    spread[heard] = 1.4826 * np.nanmedian(np.abs(err[:, heard] - bias[heard]), axis=0)
    return SurveyBiases(bias=bias, spread=spread, count=count)
