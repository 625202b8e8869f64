"""A per-scan floor classifier learned from the site's own survey scans.

The radio map's floor evidence asks how well a scan matches the survey
scans *somewhere* on each floor. Where a floor is thinly surveyed, the scan
of a walker there often matches a well-surveyed floor's scans better than
its own floor's few, and a tracker started on that evidence holds the
wrong floor for the whole walk. A model of each access point's levels
(which access point, how loud) learns the same surveyed places and fails in
the same gaps.

What carries over to unsurveyed places is where the access points are: an
access point belongs to the floor on which the survey heard it loudest (its
*home floor*), and a phone hears the access points of its own floor loudest
and most often, wherever it is on the floor. Each scan is described per
floor by the access points homed there that it hears: the loudest level,
the summed levels, their count, which floor the loudest one is homed on,
and how many of its few loudest are homed on each floor. A multinomial
logistic regression on these 5·F features, with an L2 penalty and each
floor's scans weighted alike (a thinly surveyed floor counts as much as a
thick one), gives ln p(floor | scan). It is fitted by L-BFGS from a zero
start on scans in the order given, so the same survey gives the same model.
Its log-probabilities, tempered, are one scan's floor evidence in the HMM's
floor filter (``app.engine.hmm.floor_filter``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import minimize
from scipy.special import log_softmax, softmax

N_FEATURE_KINDS = 5
"""Features per floor: loudest level, summed levels, count, loudest's home, ranks' homes."""


@dataclass(frozen=True)
class FloorClassifierParams:
    """Constants of the per-scan floor classifier.

    Attributes
    ----------
    l2 : float
        L2 penalty on the weights, per unit of (floor-balanced) scan weight:
        larger keeps the model from trusting one feature alone.
    level_scale_db : float
        A level (dB above the floor) is divided by this to make a feature;
        summed levels by ten times this.
    count_scale : float
        Access points heard per floor are divided by this to make a feature.
    home_readings : int
        An access point's home floor is the one where the mean of its this
        many strongest survey readings is highest.
    home_min_readings : int
        Floors with fewer survey readings of an access point are not its home.
    loudest : int
        How many of a scan's loudest access points vote for their home floors.
    max_iterations : int
        L-BFGS iterations at most.
    """

    l2: float = 1e-3
    level_scale_db: float = 30.0
    count_scale: float = 10.0
    home_readings: int = 10
    home_min_readings: int = 3
    loudest: int = 5
    max_iterations: int = 300


@dataclass(frozen=True, eq=False)
class FloorClassifier:
    """Weights of the fitted classifier over home-floor features.

    ``column`` maps a site transmitter index to its reference column (-1:
    none) and ``home`` a column to its home floor (-1: none); ``weights`` is
    (5·F, F) and ``bias`` (F,), floors in the order of the labels it was
    fitted on.
    """

    column: np.ndarray
    home: np.ndarray
    weights: np.ndarray
    bias: np.ndarray
    params: FloorClassifierParams

    @property
    def n_floors(self) -> int:
        """Number of floors it tells apart."""
        return int(self.bias.size)

    def log_probs(self, tx: np.ndarray, level: np.ndarray) -> np.ndarray:
        """Return ln p(floor | scan), (F,), for a scan's transmitters and levels.

        Levels are dB above the floor, as ``ReferenceScans`` keeps them; the
        answer is uniform when no transmitter heard has a home floor.
        """
        tx = np.asarray(tx, dtype=np.int64)
        inside = (tx >= 0) & (tx < self.column.size)
        col = np.full(tx.size, -1, dtype=np.int64)
        col[inside] = self.column[tx[inside]]
        home = np.where(col >= 0, self.home[np.maximum(col, 0)], -1)
        level = np.asarray(level, dtype=float)
        used = (home >= 0) & (level > 0)
        if not used.any():
            return np.full(self.n_floors, -np.log(self.n_floors))
        scan = np.zeros(int(used.sum()), dtype=np.int64)
        x = home_features(scan, home[used], level[used], 1, self.n_floors, self.params)[0]
        # z = b + x W
        return log_softmax(self.bias + x @ self.weights)


def home_floors(
    references: sparse.csr_matrix, labels: np.ndarray, n_floors: int, params: FloorClassifierParams
) -> np.ndarray:
    """Return each reference column's home floor (-1: heard on no floor often enough).

    ``references`` is (S, columns) of levels (dB above the floor), ``labels``
    each scan's floor.
    """
    coo = references.tocoo()
    floor = np.asarray(labels, dtype=np.int64)[coo.row]
    level = coo.data.astype(float)
    n_cols = references.shape[1]
    # the strongest readings first within each (column, floor)
    order = np.lexsort((-level, floor, coo.col))
    col, floor, level = coo.col[order].astype(np.int64), floor[order], level[order]
    key = col * n_floors + floor
    first = np.searchsorted(key, key, side="left")
    rank = np.arange(key.size) - first
    top = rank < params.home_readings
    sums = np.bincount(key[top], weights=level[top], minlength=n_cols * n_floors)
    counts = np.bincount(key, minlength=n_cols * n_floors)
    taken = np.minimum(counts, params.home_readings)
    mean = np.where(
        counts >= params.home_min_readings, sums / np.maximum(taken, 1), -np.inf
    ).reshape(n_cols, n_floors)
    home = np.argmax(mean, axis=1)
    return np.where(np.isfinite(mean.max(axis=1, initial=-np.inf)), home, -1)


def home_features(
    scan: np.ndarray,
    home: np.ndarray,
    level: np.ndarray,
    n_scans: int,
    n_floors: int,
    params: FloorClassifierParams,
) -> np.ndarray:
    """Return the (n_scans, 5·F) home-floor features of readings (scan, home floor, level).

    Readings without a home floor (-1) must be left out by the caller.
    """
    f = n_floors
    out = np.zeros((n_scans, N_FEATURE_KINDS * f))
    cell = scan * f + home
    loudest = np.zeros(n_scans * f)
    np.maximum.at(loudest, cell, level)
    out[:, :f] = loudest.reshape(n_scans, f) / params.level_scale_db
    summed = np.bincount(cell, weights=level, minlength=n_scans * f).reshape(n_scans, f)
    out[:, f : 2 * f] = summed / (10.0 * params.level_scale_db)
    count = np.bincount(cell, minlength=n_scans * f).reshape(n_scans, f)
    out[:, 2 * f : 3 * f] = count / params.count_scale
    # each scan's readings loudest first: the first votes alone, the first few together
    order = np.lexsort((-level, scan))
    scan, home = scan[order], home[order]
    rank = np.arange(scan.size) - np.searchsorted(scan, scan, side="left")
    first = rank == 0
    out[scan[first], 3 * f + home[first]] = 1.0
    few = rank < params.loudest
    votes = np.bincount(scan[few] * f + home[few], minlength=n_scans * f).reshape(n_scans, f)
    out[:, 4 * f :] = votes / params.loudest
    return out


def fit_floor_classifier(
    references: sparse.csr_matrix,
    labels: np.ndarray,
    n_floors: int,
    column: np.ndarray,
    params: FloorClassifierParams,
) -> FloorClassifier:
    """Fit the classifier to survey scans.

    Parameters
    ----------
    references : csr_matrix, shape (S, columns)
        Each survey scan's levels (dB above the floor) on the reference columns.
    labels : ndarray of int, shape (S,)
        Each scan's floor, in [0, n_floors).
    n_floors : int
        Number of floors.
    column : ndarray of int
        Site transmitter index to reference column (-1: none).
    params : FloorClassifierParams
        Constants.
    """
    labels = np.asarray(labels, dtype=np.int64)
    n_scans = references.shape[0]
    home = home_floors(references, labels, n_floors, params)
    coo = references.tocoo()
    keep = (home[coo.col] >= 0) & (coo.data > 0)
    x = home_features(
        coo.row[keep].astype(np.int64),
        home[coo.col[keep]],
        coo.data[keep].astype(float),
        n_scans,
        n_floors,
        params,
    )
    n_features = x.shape[1]
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
        return value, np.concatenate([grad_w.ravel(), grad_b])

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
        home=home,
        weights=theta[: n_features * n_floors].reshape(n_features, n_floors).copy(),
        bias=theta[n_features * n_floors :].copy(),
        params=params,
    )
