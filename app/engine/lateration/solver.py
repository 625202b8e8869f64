"""Robust Gauss–Newton position fixes from UWB ranges or RSSI (Grinyak 2020).

Grinyak (2020) linearises the measurement equations around a
reference solution and solves them by Gauss–Newton; the fix is then checked
for observability, stability and accuracy (``accuracy``).

Non-line-of-sight readings (a UWB range through a wall, an RSSI behind a
body) are outliers of one sign. After a few plain iterations the weights are
re-computed each iteration from the standardised residuals (Huber or Cauchy
IRLS), so one bad emitter among many loses its pull on the fix.

Everything is vectorised over a batch of independent problems (epochs of a
recording, cells of an accuracy map); missing readings are NaN. A single
problem is a batch of one. Nothing here raises on bad geometry or data: each
problem gets a :class:`Status` instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Literal

import numpy as np

from app.engine.lateration.accuracy import (
    Model,
    covariance_checks,
    critical_condition,
    predict,
    rank_tolerance,
)

Loss = Literal["linear", "huber", "cauchy"]


@dataclass(frozen=True)
class LaterationParams:
    """Tunable constants of the Gauss–Newton solver and its checks.

    Attributes
    ----------
    max_iter : int
        Gauss–Newton iterations at most.
    tol_m : float
        Converged when the step is shorter than this (m).
    loss : {"linear", "huber", "cauchy"}
        Robust loss of the standardised residual s = (measured - predicted) / std.
    loss_scale : float
        k of the loss (in units of std): Huber is quadratic below k, linear
        above; Cauchy weighs 1 / (1 + (s/k)²). 3 leaves the 10–30 cm
        systematic range biases of real UWB (2–3 σ) almost at full weight
        and cuts gross NLOS errors (metres); the textbook 1.345 down-weights
        the longest-biased anchors and costs 1–4 cm RMS on the trolley
        recording.
    plain_iterations : int
        Iterations with unit weights before IRLS starts, so that a bad start
        point does not down-weight the good readings.
    min_redundancy : int
        Readings needed beyond the number of unknowns: 1 means at least 3
        emitters in 2-D, 4 in 3-D (fewer leave a mirror ambiguity).
    degenerate_ratio : float
        The emitters heard are collinear (2-D) or on one line (3-D) when the
        second singular value of their centred coordinates is below this
        fraction of the first: the fix then has a mirror twin.
    min_distance_m : float
        Distances are floored at this (m) so that a start on an emitter
        does not divide by zero.
    max_halvings : int
        Step halvings tried when a full Gauss–Newton step increases the cost.
    max_step_m : float
        Longest Gauss–Newton step (m): far from the emitters the RSSI cost is
        flat and an unclipped step can run off to infinity.
    """

    max_iter: int = 20
    tol_m: float = 1e-3
    loss: Loss = "huber"
    loss_scale: float = 3.0
    plain_iterations: int = 2
    min_redundancy: int = 1
    degenerate_ratio: float = 0.02
    min_distance_m: float = 0.01
    max_halvings: int = 4
    max_step_m: float = 5.0


class Status(IntEnum):
    """Outcome of one least-squares problem; only ``OK`` fixes are usable as they are."""

    OK = 0
    TOO_FEW = 1
    """Fewer readings than unknowns plus ``min_redundancy``: no fix."""
    DEGENERATE = 2
    """Emitters collinear: the fix may be the mirror image of the truth."""
    UNOBSERVABLE = 3
    """H is rank deficient at the solution (e.g. object in the emitters' plane)."""
    ILL_CONDITIONED = 4
    """cond(H) above the paper's critical μ*: round-off dominates."""
    NOT_CONVERGED = 5
    """Gauss–Newton hit ``max_iter`` still moving."""


@dataclass(frozen=True)
class LaterationResult:
    """One least-squares fix.

    Attributes
    ----------
    position : ndarray, shape (3,)
        x, y, z (m); z is the given height when ``dims`` is 2; NaN without a fix.
    covariance : ndarray, shape (3, 3)
        D = (Hᵀ W Q⁻¹ H)⁻¹ (m²) with the final robust weights W; the z row and
        column are 0 when the height was given (``dims`` 2); NaN when singular.
    dims : int
        Unknowns solved for: 3, or 2 when the height was known or 3-D was
        unobservable and the solver fell back to the known height.
    status : Status
        Outcome of the checks.
    cond : float
        Condition number of the whitened H (∞ when rank deficient).
    residuals : ndarray, shape (K,)
        Measured minus predicted (m or dB) at the solution; NaN where missing.
    weights : ndarray, shape (K,)
        Final robust weights in [0, 1]; 0 where missing.
    iterations : int
        Gauss–Newton iterations run.
    converged : bool
        The last step was shorter than ``tol_m``.
    """

    position: np.ndarray
    covariance: np.ndarray
    dims: int
    status: Status
    cond: float
    residuals: np.ndarray
    weights: np.ndarray
    iterations: int
    converged: bool

    @property
    def ok(self) -> bool:
        """Whether the fix passed every check."""
        return self.status == Status.OK

    @property
    def sigma(self) -> np.ndarray:
        """Standard deviations (m) of x, y, z from the diagonal of D, shape (3,)."""
        return np.sqrt(np.diagonal(self.covariance))


@dataclass(frozen=True)
class LaterationBatch:
    """Fixes of N independent problems, the fields of :class:`LaterationResult` stacked.

    Shapes: position (N, 3), covariance (N, 3, 3), dims (N,), status (N,),
    cond (N,), residuals (N, K), weights (N, K), iterations (N,), converged (N,).
    """

    position: np.ndarray
    covariance: np.ndarray
    dims: np.ndarray
    status: np.ndarray
    cond: np.ndarray
    residuals: np.ndarray
    weights: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray

    def __len__(self) -> int:
        """Return the number of problems N."""
        return int(self.position.shape[0])

    @property
    def ok(self) -> np.ndarray:
        """Boolean mask of the fixes that passed every check, shape (N,)."""
        return self.status == Status.OK

    def item(self, i: int) -> LaterationResult:
        """Return problem ``i`` as a :class:`LaterationResult`."""
        return LaterationResult(
            position=self.position[i],
            covariance=self.covariance[i],
            dims=int(self.dims[i]),
            status=Status(int(self.status[i])),
            cond=float(self.cond[i]),
            residuals=self.residuals[i],
            weights=self.weights[i],
            iterations=int(self.iterations[i]),
            converged=bool(self.converged[i]),
        )


def robust_weights(s: np.ndarray, loss: Loss, k: float) -> np.ndarray:
    """Return IRLS weights ψ(s)/s for standardised residuals ``s`` (any shape)."""
    a = np.abs(s)
    if loss == "huber":
        # w = 1 for |s| ≤ k, k/|s| beyond
        return np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))
    if loss == "cauchy":
        # w = 1 / (1 + (s/k)²)
        return 1.0 / (1.0 + (s / k) ** 2)
    return np.ones_like(s)


def robust_cost(s: np.ndarray, loss: Loss, k: float) -> np.ndarray:
    """Return ρ(s) summed over the last axis (the objective IRLS minimises)."""
    a = np.abs(s)
    if loss == "huber":
        # ρ = s²/2 for |s| ≤ k, k|s| − k²/2 beyond
        rho = np.where(a <= k, 0.5 * s * s, k * a - 0.5 * k * k)
    elif loss == "cauchy":
        # ρ = (k²/2) ln(1 + (s/k)²)
        rho = 0.5 * k * k * np.log1p((s / k) ** 2)
    else:
        rho = 0.5 * s * s
    return rho.sum(axis=-1)


def _pinv_step(Hw: np.ndarray, rw: np.ndarray) -> np.ndarray:
    """Return δ = Hw⁺ rw (N, d), leaving numerically unobservable directions unchanged."""
    u, s, vt = np.linalg.svd(Hw, full_matrices=False)
    tol = rank_tolerance(Hw.shape[-2], Hw.shape[-1]) * np.maximum(s[..., :1], 1e-300)
    inv = np.where(s > tol, 1.0 / np.where(s > 0, s, 1.0), 0.0)
    # δ = V S⁺ Uᵀ r
    return np.einsum("nji,nj,nkj,nk->ni", vt, inv, u, rw)


def _degenerate(emitters: np.ndarray, used: np.ndarray, dims: int, ratio: float) -> np.ndarray:
    """Return where the heard emitters lie on one line (in the solved dimensions), shape (N,)."""
    n = np.maximum(used.sum(axis=1), 1)
    xyz = emitters[None, :, :dims] * used[..., None]
    # centred coordinates of the heard emitters (zero rows for the others)
    mean = xyz.sum(axis=1) / n[:, None]
    centred = (emitters[None, :, :dims] - mean[:, None, :]) * used[..., None]
    s = np.linalg.svd(centred, compute_uv=False)
    return s[:, 1] <= ratio * np.maximum(s[:, 0], 1e-300)


def solve(
    model: Model,
    emitters: np.ndarray,
    obs: np.ndarray,
    std: np.ndarray,
    *,
    A: np.ndarray | None = None,
    B: np.ndarray | None = None,
    height: np.ndarray | float | None = None,
    dims: int = 3,
    x0: np.ndarray | None = None,
    params: LaterationParams = LaterationParams(),
) -> LaterationBatch:
    """Solve N least-squares position problems at once by robust Gauss–Newton.

    Parameters
    ----------
    model : {"range", "rssi"}
    emitters : ndarray, shape (K, 3)
        Anchor or transmitter positions (m).
    obs : ndarray, shape (N, K)
        Ranges (m) or mean RSSI (dBm); NaN where not heard.
    std : ndarray, shape (K,) or (N, K)
        Standard deviation of each reading (m or dB; σ/√M for a mean of M).
    A, B : ndarray, shape (K,), optional
        Path-loss parameters for ``rssi``.
    height : float or ndarray (N,), optional
        Known z (m). With ``dims`` 2 it is the fixed height; with ``dims`` 3
        it is the start height and the fallback when 3-D is unobservable.
    dims : {2, 3}
        Unknowns: x, y (height known) or x, y, z.
    x0 : ndarray, shape (N, 3), optional
        Start points; default: centroid of the heard emitters at ``height``
        (or at their mean height).
    params : LaterationParams

    Returns
    -------
    LaterationBatch
    """
    emitters = np.asarray(emitters, dtype=float)
    obs = np.atleast_2d(np.asarray(obs, dtype=float))
    N, K = obs.shape
    std = np.broadcast_to(np.asarray(std, dtype=float), (N, K))
    heights = None if height is None else np.broadcast_to(np.asarray(height, dtype=float), (N,))
    if dims == 2 and heights is None:
        raise ValueError("2-D lateration needs the height")
    used = np.isfinite(obs) & np.isfinite(std) & (std > 0)
    if model == "rssi":
        if A is None or B is None:
            raise ValueError("the rssi model needs A and B")
        A = np.asarray(A, dtype=float)
        B = np.asarray(B, dtype=float)
        used &= (np.isfinite(A) & np.isfinite(B))[None, :]
    if x0 is None:
        n = np.maximum(used.sum(axis=1), 1)
        x0 = (used.astype(float) @ emitters) / n[:, None]
        if heights is not None:
            x0[:, 2] = heights
    x = np.array(x0, dtype=float)
    if dims == 2:
        x[:, 2] = heights
    batch = _gauss_newton(model, emitters, obs, std, used, A, B, x, dims, params)
    fall_back = (batch.status == Status.UNOBSERVABLE) & (dims == 3) & (heights is not None)
    if fall_back.any():
        idx = np.flatnonzero(fall_back)
        start = batch.position[idx].copy()
        start[:, 2] = heights[idx]  # type: ignore[index]
        flat = _gauss_newton(
            model,
            emitters,
            obs[idx],
            std[idx],
            used[idx],
            A,
            B,
            start,
            2,
            params,
        )
        for name in LaterationBatch.__dataclass_fields__:
            getattr(batch, name)[idx] = getattr(flat, name)
    return batch


def _gauss_newton(
    model: Model,
    emitters: np.ndarray,
    obs: np.ndarray,
    std: np.ndarray,
    used: np.ndarray,
    A: np.ndarray | None,
    B: np.ndarray | None,
    x: np.ndarray,
    dims: int,
    p: LaterationParams,
) -> LaterationBatch:
    """Run robust Gauss–Newton from ``x`` (N, 3) on the ``dims`` first coordinates."""
    N, K = obs.shape
    safe_std = np.where(used, std, 1.0)
    obs0 = np.where(used, obs, 0.0)
    weights = used.astype(float)
    iterations = np.zeros(N, dtype=np.int64)
    converged = np.zeros(N, dtype=bool)
    active = used.sum(axis=1) >= dims + p.min_redundancy
    halvings = 0.5 ** np.arange(p.max_halvings + 1)

    def standardised(points: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, J = predict(model, points, emitters, A, B, p.min_distance_m)
        # s = (z − h(p)) / σ, 0 where not heard
        return np.where(used[rows], (obs0[rows] - h) / safe_std[rows], 0.0), J

    for it in range(p.max_iter):
        run = active & ~converged
        if not run.any():
            break
        idx = np.flatnonzero(run)
        s, J = standardised(x[idx], idx)
        loss: Loss = p.loss if it >= p.plain_iterations else "linear"
        w = robust_weights(s, loss, p.loss_scale) * used[idx]
        weights[idx] = w
        sw = np.sqrt(w)
        # whitened system: (√W Q^(−½) H) δ = √W s
        Hw = J[..., :dims] * (sw / safe_std[idx])[..., None]
        rw = s * sw
        step = _pinv_step(Hw, rw)
        # δ ← δ · min(1, δ_max / |δ|)
        norm = np.linalg.norm(step, axis=1, keepdims=True)
        step = step * np.minimum(1.0, p.max_step_m / np.maximum(norm, 1e-300))
        full = np.zeros((idx.size, 3))
        full[:, :dims] = step
        # backtracking: the largest of δ, δ/2, δ/4, … that does not raise Σρ(s)
        cost0 = robust_cost(s, loss, p.loss_scale)
        trial = x[idx][None] + halvings[:, None, None] * full[None]
        s_trial, _ = standardised(trial.reshape(-1, 3), np.tile(idx, halvings.size))
        cost = robust_cost(s_trial, loss, p.loss_scale).reshape(halvings.size, idx.size)
        better = cost <= cost0[None] + 1e-12
        pick = np.where(better.any(axis=0), np.argmax(better, axis=0), halvings.size - 1)
        moved = halvings[pick][:, None] * full
        x[idx] += moved
        iterations[idx] = it + 1
        converged[idx] = np.linalg.norm(moved, axis=1) < p.tol_m

    s, J = standardised(x, np.arange(N))
    final_loss: Loss = p.loss if p.max_iter > p.plain_iterations else "linear"
    weights = np.where(active[:, None], robust_weights(s, final_loss, p.loss_scale) * used, 0.0)
    Hw = J[..., :dims] * (np.sqrt(weights) / safe_std)[..., None]
    cov_d, cond, rank = covariance_checks(Hw)
    cov = np.zeros((N, 3, 3))
    cov[:, :dims, :dims] = cov_d
    residuals = np.where(used, s * safe_std, np.nan)

    status = np.full(N, Status.OK, dtype=np.int8)
    status[~converged] = Status.NOT_CONVERGED
    status[cond >= critical_condition(dims)] = Status.ILL_CONDITIONED
    status[rank < dims] = Status.UNOBSERVABLE
    status[_degenerate(emitters, used, dims, p.degenerate_ratio)] = Status.DEGENERATE
    status[~active] = Status.TOO_FEW
    position = x.copy()
    position[~active] = np.nan
    cov[~active] = np.nan
    cond[~active] = np.nan
    return LaterationBatch(
        position=position,
        covariance=cov,
        dims=np.full(N, dims, dtype=np.int8),
        status=status,
        cond=cond,
        residuals=residuals,
        weights=weights,
        iterations=iterations,
        converged=converged,
    )


def laterate_ranges(
    anchors: np.ndarray,
    ranges: np.ndarray,
    std: np.ndarray | float,
    *,
    height: float | None = None,
    dims: int = 3,
    x0: np.ndarray | None = None,
    params: LaterationParams = LaterationParams(),
) -> LaterationResult:
    """Fix one position from two-way ranges (m) to ``anchors`` (K, 3); NaN ranges are ignored.

    ``std`` is each range's standard deviation (m); see :func:`solve` for the rest.
    """
    ranges = np.asarray(ranges, dtype=float)[None, :]
    start = None if x0 is None else np.asarray(x0, dtype=float)[None, :]
    std_arr = np.broadcast_to(np.asarray(std, dtype=float), ranges.shape[1:])
    return solve(
        "range", anchors, ranges, std_arr, height=height, dims=dims, x0=start, params=params
    ).item(0)


def laterate_rssi(
    transmitters: np.ndarray,
    rssi: np.ndarray,
    A: np.ndarray,
    B: np.ndarray,
    sigma: np.ndarray,
    count: np.ndarray | int = 1,
    *,
    height: float | None = None,
    dims: int = 3,
    x0: np.ndarray | None = None,
    params: LaterationParams = LaterationParams(),
) -> LaterationResult:
    """Fix one position from the mean RSSI (dBm) of ``count`` readings per transmitter.

    Each mean has std σ/√M (M = ``count``); NaN means or zero counts are ignored.
    ``transmitters`` (K, 3), ``A``, ``B``, ``sigma`` (K,) follow ``rssi = A - B ln r``.
    """
    rssi = np.asarray(rssi, dtype=float)[None, :]
    count = np.broadcast_to(np.asarray(count, dtype=float), rssi.shape[1:])
    # σ_mean = σ / √M
    std = np.where(
        count > 0, np.asarray(sigma, dtype=float) / np.sqrt(np.maximum(count, 1)), np.nan
    )
    start = None if x0 is None else np.asarray(x0, dtype=float)[None, :]
    return solve(
        "rssi",
        transmitters,
        rssi,
        std,
        A=np.asarray(A, dtype=float),
        B=np.asarray(B, dtype=float),
        height=height,
        dims=dims,
        x0=start,
        params=params,
    ).item(0)
