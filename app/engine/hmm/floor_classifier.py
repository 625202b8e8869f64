"""A per-scan floor classifier learned from the site's own survey scans.

The radio map's floor evidence asks how well a scan matches the survey
scans *somewhere* on each floor. Where a floor is thinly surveyed, the scan
of a walker there often matches a well-surveyed floor's scans better than
its own floor's few, and a tracker started on that evidence holds the
wrong floor for the whole walk. Which access points a scan hears, and how
loudly, separates floors better than any position fingerprint: an access
point two floors away is rarely heard, or heard faintly. A discriminative
model says that directly.

The model is a multinomial logistic regression on the scan's levels (dB
above ``floor_dbm``, scaled) of the transmitters the survey heard often
enough, with an L2 penalty, each floor's scans weighted alike so that a
thinly surveyed floor counts as much as a thick one. It is fitted by
L-BFGS from a zero start on scans in the order given, so the same survey
gives the same model. Its log-probabilities, tempered, are one scan's
floor evidence in the HMM's floor filter (``app.engine.hmm.floor_filter``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import minimize
from scipy.special import log_softmax, softmax


@dataclass(frozen=True)
class FloorClassifierParams:
    """Constants of the per-scan floor classifier.

    Attributes
    ----------
    l2 : float
        L2 penalty on the weights, per unit of (floor-balanced) scan weight:
        larger keeps the model from trusting one access point alone.
    level_scale_db : float
        A level (dB above the floor) is divided by this to make a feature.
    max_iterations : int
        L-BFGS iterations at most.
    """

    l2: float = 1e-3
    level_scale_db: float = 30.0
    max_iterations: int = 300


@dataclass(frozen=True, eq=False)
class FloorClassifier:
    """Weights of the fitted classifier over reference-scan columns.

    ``column`` maps a site transmitter index to its feature (-1: not a
    feature); ``weights`` is (n_features, F) and ``bias`` (F,), floors in the
    order of the labels it was fitted on.
    """

    column: np.ndarray
    weights: np.ndarray
    bias: np.ndarray
    level_scale_db: float

    @property
    def n_floors(self) -> int:
        """Number of floors it tells apart."""
        return int(self.bias.size)

    def log_probs(self, tx: np.ndarray, level: np.ndarray) -> np.ndarray:
        """Return ln p(floor | scan), (F,), for a scan's transmitters and levels.

        Levels are dB above the floor, as ``ReferenceScans`` keeps them; the
        answer is uniform when no transmitter is a feature.
        """
        tx = np.asarray(tx, dtype=np.int64)
        inside = (tx >= 0) & (tx < self.column.size)
        col = np.full(tx.size, -1, dtype=np.int64)
        col[inside] = self.column[tx[inside]]
        used = col >= 0
        if not used.any():
            return np.full(self.n_floors, -np.log(self.n_floors))
        x = np.asarray(level, dtype=float)[used] / self.level_scale_db
        # z = b + Σ_a x_a W_a
        z = self.bias + x @ self.weights[col[used]]
        return log_softmax(z)


def fit_floor_classifier(
    scan_features: sparse.csr_matrix,
    labels: np.ndarray,
    n_floors: int,
    column: np.ndarray,
    params: FloorClassifierParams,
) -> FloorClassifier:
    """Fit the classifier to survey scans.

    Parameters
    ----------
    scan_features : csr_matrix, shape (S, n_features)
        Each scan's levels (dB above the floor) on the feature columns.
    labels : ndarray of int, shape (S,)
        Each scan's floor, in [0, n_floors).
    n_floors : int
        Number of floors.
    column : ndarray of int
        Site transmitter index to feature column (-1: none).
    params : FloorClassifierParams
        Constants.
    """
    n_scans, n_features = scan_features.shape
    x = (scan_features / params.level_scale_db).tocsr()
    labels = np.asarray(labels, dtype=np.int64)
    counts = np.bincount(labels, minlength=n_floors).astype(float)
    # each floor weighs alike: s_i = S / (F_seen · n_floor(i))
    seen = counts > 0
    share = np.where(seen, n_scans / (max(int(seen.sum()), 1) * np.maximum(counts, 1.0)), 0.0)
    s = share[labels]
    total = float(s.sum())
    y = np.zeros((n_scans, n_floors))
    y[np.arange(n_scans), labels] = 1.0

    def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
        w = theta[: n_features * n_floors].reshape(n_features, n_floors)
        b = theta[n_features * n_floors :]
        z = x @ w + b
        logp = log_softmax(z, axis=1)
        # L = -Σ s_i ln p_i,y / Σ s + λ/2 |W|²
        value = -float(np.sum(s * logp[np.arange(n_scans), labels])) / total
        value += 0.5 * params.l2 * float(np.sum(w * w))
        r = (softmax(z, axis=1) - y) * (s / total)[:, None]
        grad_w = x.T @ r + params.l2 * w
        grad_b = r.sum(axis=0)
        return value, np.concatenate([np.asarray(grad_w).ravel(), grad_b])

    theta0 = np.zeros(n_features * n_floors + n_floors)
    if n_scans and n_floors > 1:
        result = minimize(
            loss,
            theta0,
            jac=True,
            method="L-BFGS-B",
            options={"maxiter": params.max_iterations},
        )
        theta = result.x
    else:
        theta = theta0
    return FloorClassifier(
        column=np.asarray(column, dtype=np.int64),
        weights=theta[: n_features * n_floors].reshape(n_features, n_floors).copy(),
        bias=theta[n_features * n_floors :].copy(),
        level_scale_db=params.level_scale_db,
    )
