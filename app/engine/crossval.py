"""Held-out accuracy of a fingerprint radio map by walk-level cross-validation.

Scans of one survey walk are strongly correlated (same phone, same day, the
same line walked), so holding out single scans would flatter the map: each
held-out scan would sit between two training scans of its own walk. Folds are
therefore whole walks: walk ``w`` is in fold ``w mod k``; each fold's scans are
located by WKNN on maps built from the other folds only, and their errors
pooled. The same folds choose the site's building-dependent constants: the
number of WKNN neighbours with the lowest held-out error, and the emission
weight under which one scan's HMM posterior best covers the surveyed position.

WKNN is vectorised over the held-out scans: with readings shifted by the
missing level, ``d² = |v|² - 2 S Vᵀ + |s|²`` is one dense matrix product per
floor map for a chunk of scans.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import sparse
from scipy.special import logsumexp

from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.params import HmmParams
from app.engine.plan import FloorPlan
from app.engine.radiomap import RadioMap, RadioMapParams, Survey, build_radio_map
from app.engine.wknn import Fingerprints, WknnParams

CHUNK = 512
"""Held-out scans located per matrix product (bounds the (scans × points) distance block)."""


@dataclass(frozen=True)
class HeldOut:
    """Errors of every held-out scan located by WKNN with one k.

    Attributes
    ----------
    error_m : ndarray, shape (n,)
        Horizontal distance (m) between the WKNN position and the surveyed one.
    floor_ok : ndarray of bool, shape (n,)
        Whether the voted floor is the surveyed floor.
    scan : ndarray of int, shape (n,)
        Row of each scan in the survey.
    folds : int
        Folds used.
    """

    error_m: np.ndarray
    floor_ok: np.ndarray
    scan: np.ndarray
    folds: int


@dataclass(frozen=True)
class CrossValidation:
    """Held-out figures of every candidate constant, pooled over walk-level folds.

    Attributes
    ----------
    by_k : dict of int to HeldOut
        WKNN errors of every candidate number of neighbours.
    emission_score : dict of float to float
        Mean log-score of the surveyed position under one scan's emission
        posterior, per candidate emission weight (higher is better); empty
        when not asked for.
    floor_score : dict of float to float
        Mean log-probability of the surveyed floor under one scan's floor
        posterior, per candidate weight.
    emission_scans : int
        Held-out scans the emission scores average.
    """

    by_k: dict[int, HeldOut]
    emission_score: dict[float, float]
    floor_score: dict[float, float]
    emission_scans: int

    def best_k(self) -> int:
        """Return the k with the lowest mean held-out error (the smaller k on ties)."""
        return min(self.by_k, key=lambda k: (float(np.mean(self.by_k[k].error_m)), k))

    def best_emission_weight(self) -> float | None:
        """Return the emission weight with the best held-out log-score, if any was scored."""
        return _best(self.emission_score)

    def best_floor_weight(self) -> float | None:
        """Return the floor evidence weight with the best held-out log-score, if any."""
        return _best(self.floor_score)


def _best(scores: dict[float, float]) -> float | None:
    """Return the weight of the highest score (the smaller weight on ties), None for none."""
    return max(scores, key=lambda w: (scores[w], -w)) if scores else None


def nearest_fingerprints(
    fingerprints: Fingerprints, survey: Survey, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Return the ``k`` nearest fingerprints of every scan of ``survey``, nearest first.

    Floor by floor, each chunk of scans is densified over the floor's
    transmitters so the distances are one BLAS product, and only the floor's
    k nearest are kept; the k nearest overall are among those.

    Returns
    -------
    distance : ndarray, shape (S, k')
        RSSI distances (dB), ascending; k' = min(k, number of points).
    index : ndarray of int, shape (S, k')
        Their rows in ``fingerprints``.
    """
    n = survey.n_scans
    # s = max(rssi - missing, 0) per (scan, transmitter)
    s_val = np.maximum(survey.reading_rssi - fingerprints.missing, 0.0)
    n_tx = max(int(survey.reading_tx.max(initial=-1)) + 1, fingerprints.columns[0].size)
    S = sparse.csr_matrix((s_val, (survey.reading_scan, survey.reading_tx)), shape=(n, n_tx))
    s_norm = np.asarray(S.multiply(S).sum(axis=1)).ravel()
    n_maps = len(fingerprints.values)
    cand_d = np.full((n, n_maps * k), np.inf)
    cand_i = np.zeros((n, n_maps * k), dtype=np.int64)
    offset = 0
    for f, (lookup, values, norms) in enumerate(
        zip(fingerprints.columns, fingerprints.values, fingerprints.norms, strict=True)
    ):
        cols = np.flatnonzero(lookup >= 0)
        cols = cols[cols < n_tx]
        V = values[lookup[cols]].astype(np.float64)
        S_f = S[:, cols].tocsr()
        kf = min(k, norms.size)
        for lo in range(0, n, CHUNK):
            hi = min(lo + CHUNK, n)
            # d² = |v|² - 2 v·s + |s|²
            dot = S_f[lo:hi].toarray() @ V
            d2 = np.maximum(norms[None, :] - 2.0 * dot + s_norm[lo:hi, None], 0.0)
            part = np.argpartition(d2, kf - 1, axis=1)[:, :kf]
            cand_d[lo:hi, f * k : f * k + kf] = np.sqrt(np.take_along_axis(d2, part, axis=1))
            cand_i[lo:hi, f * k : f * k + kf] = part + offset
        offset += norms.size
    k = min(k, offset)
    order = np.argsort(cand_d, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(cand_d, order, axis=1), np.take_along_axis(cand_i, order, axis=1)


def wknn_estimates(
    fingerprints: Fingerprints, distance: np.ndarray, index: np.ndarray, k: int, eps_db: float
) -> tuple[np.ndarray, np.ndarray]:
    """Return WKNN positions and voted floors from each scan's first ``k`` nearest fingerprints.

    Returns
    -------
    xy : ndarray, shape (S, 2)
        Weighted mean position (m) of the neighbours on the voted floor.
    floor : ndarray of int, shape (S,)
        Voted floor index.
    """
    dk, near = distance[:, :k], index[:, :k]
    # w_i = 1 / (d_i + ε)
    w = 1.0 / (dk + eps_db)
    floors = fingerprints.floor[near]
    levels = np.unique(fingerprints.floor)
    votes = np.stack([(w * (floors == f)).sum(axis=1) for f in levels], axis=1)
    best = levels[np.argmax(votes, axis=1)]
    w_on = w * (floors == best[:, None])
    # x = Σ w_i x_i / Σ w_i over the voted floor's neighbours
    xy = np.einsum("sk,skd->sd", w_on, fingerprints.xy[near]) / w_on.sum(axis=1, keepdims=True)
    return xy, best.astype(np.int64)


def wknn_scans(
    fingerprints: Fingerprints, survey: Survey, params: WknnParams
) -> tuple[np.ndarray, np.ndarray]:
    """Locate every scan of ``survey`` by WKNN (same answer as ``wknn`` scan by scan)."""
    distance, index = nearest_fingerprints(fingerprints, survey, params.k)
    return wknn_estimates(fingerprints, distance, index, params.k, params.eps_db)


def walk_folds(
    survey: Survey, plans: Mapping[int, FloorPlan], params: RadioMapParams, folds: int
) -> Iterator[tuple[tuple[RadioMap, ...], np.ndarray]]:
    """Yield each fold's radio maps, built without its walks, and the mask of its scans.

    Walk ``w`` is in fold ``w mod k``, k = min(folds, walks); nothing is
    yielded with fewer than two walks. Folds whose training part maps no
    floor, or that hold no scan, are skipped.
    """
    walks = np.unique(survey.scan_walk)
    k = min(folds, walks.size)
    if k < 2:
        return
    fold_of_scan = survey.scan_walk % k
    for fold in range(k):
        test = fold_of_scan == fold
        train = survey.select(~test)
        maps: list[RadioMap] = []
        for f in np.unique(train.scan_floor):
            try:
                m = build_radio_map(train, int(f), params, walkable=plans.get(int(f)))
            except ValueError:
                continue
            if m.n_points and m.tx.size:
                maps.append(m)
        if maps and test.any():
            yield tuple(maps), test


def emission_log_scores(
    maps: tuple[RadioMap, ...],
    held: Survey,
    hmm_params: HmmParams,
    weights: Sequence[float],
    *,
    max_scans: int,
    kernel_m: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Return summed log-scores of position and of floor per candidate weight.

    Over (up to ``max_scans``) held-out scans on mapped floors: a scan's
    emission posterior on its surveyed floor is ``p_j ∝ L_j^w``, scored by
    ``ln Σ_j p_j exp(-|x_j - x|² / 2 s²)``, how much of it lies within about
    ``kernel_m`` of the surveyed position; its floor posterior is
    ``P_f ∝ mean_j L_fj^w``, scored by ``ln P`` of the surveyed floor. The
    weight that scores best is the tempering under which one scan is as sure
    as it should be, neither spread out nor a needle beside the truth.

    Returns
    -------
    position, floor : ndarray, shape (W,)
        Summed log-scores per weight.
    n : int
        Scans scored.
    """
    model = EmissionModel(maps, replace(hmm_params, emission_weight=1.0))
    position = {m.floor: i for i, m in enumerate(maps)}
    rows = np.flatnonzero(np.isin(held.scan_floor, list(position)))
    if rows.size > max_scans:
        rows = rows[np.linspace(0, rows.size - 1, max_scans).astype(np.int64)]
    w = np.asarray(weights, dtype=float)[:, None]
    pos_total = np.zeros(w.shape[0])
    floor_total = np.zeros(w.shape[0])
    order = np.argsort(held.reading_scan, kind="stable")
    starts = np.searchsorted(held.reading_scan[order], np.arange(held.n_scans + 1))
    scored = 0
    for r in rows:
        readings = order[starts[r] : starts[r + 1]]
        if readings.size == 0:
            continue
        scored += 1
        f = position[int(held.scan_floor[r])]
        tx, rssi = held.reading_tx[readings], held.reading_rssi[readings]
        lls = model.log_likelihoods(tx, rssi)
        # ln K_j = -|x_j - x|² / 2 s²
        log_kernel = -0.5 * np.sum((model.xy[f] - held.scan_xy[r]) ** 2, axis=1) / kernel_m**2
        scaled = w * lls[f][None, :]
        pos_total += logsumexp(scaled + log_kernel[None, :], axis=1) - logsumexp(scaled, axis=1)
        # ln mean_j L_j^w per floor, then ln P(true floor)
        marginal = np.stack(
            [logsumexp(w * ll[None, :], axis=1) - np.log(ll.size) for ll in lls], axis=1
        )
        floor_total += marginal[:, f] - logsumexp(marginal, axis=1)
    return pos_total, floor_total, scored


def cross_validate(
    survey: Survey,
    plans: Mapping[int, FloorPlan],
    params: RadioMapParams,
    wknn_params: WknnParams,
    *,
    folds: int = 5,
    ks: Sequence[int] = (),
    emission: HmmParams | None = None,
    weights: Sequence[float] = (),
    emission_scans_per_fold: int = 300,
    emission_kernel_m: float = 2.0,
    fold_hook: Callable[[tuple[RadioMap, ...], np.ndarray], None] | None = None,
    progress: Callable[[float], None] | None = None,
) -> CrossValidation | None:
    """Locate each walk's scans on maps built without its fold; None with fewer than 2 walks.

    Parameters
    ----------
    survey : Survey
        Located scans of every floor; ``scan_walk`` numbers the walks.
    plans : mapping of int to FloorPlan
        Walkable area of each floor index.
    params, wknn_params
        Radio map and WKNN constants (as the service uses them).
    folds : int
        Folds at most; fewer when there are fewer walks.
    ks : sequence of int
        Candidate numbers of WKNN neighbours (``wknn_params.k`` is always one).
    emission : HmmParams, optional
        The HMM's emission constants; with ``weights``, each candidate
        emission weight is scored on held-out scans.
    weights : sequence of float
        Candidate emission weights.
    emission_scans_per_fold, emission_kernel_m
        Scans scored per fold, and the kernel of the score (m).
    fold_hook : callable, optional
        Called with each fold's maps and the mask of its held-out scans, for
        more tests of the same maps (the HMM's replay of held-out walks).
    progress : callable, optional
        Called with the fraction of folds done.
    """
    ks = sorted({wknn_params.k, *ks})
    errors: dict[int, list[np.ndarray]] = {k: [] for k in ks}
    oks: dict[int, list[np.ndarray]] = {k: [] for k in ks}
    rows: list[np.ndarray] = []
    scores = np.zeros(len(weights))
    floor_scores = np.zeros(len(weights))
    scored = 0
    n_folds = min(folds, np.unique(survey.scan_walk).size)
    for done, (maps, test) in enumerate(walk_folds(survey, plans, params, folds), start=1):
        held = survey.select(test)
        prints = Fingerprints(maps, wknn_params.missing_dbm)
        distance, index = nearest_fingerprints(prints, held, max(ks))
        for k in ks:
            xy, floor = wknn_estimates(prints, distance, index, k, wknn_params.eps_db)
            # e = |x̂ - x|
            errors[k].append(np.hypot(*(xy - held.scan_xy).T))
            oks[k].append(floor == held.scan_floor)
        rows.append(np.flatnonzero(test))
        if emission is not None and len(weights):
            total, floor_total, n = emission_log_scores(
                maps,
                held,
                emission,
                weights,
                max_scans=emission_scans_per_fold,
                kernel_m=emission_kernel_m,
            )
            scores += total
            floor_scores += floor_total
            scored += n
        if fold_hook is not None:
            fold_hook(maps, test)
        if progress is not None:
            progress(done / n_folds)
    if not rows:
        return None
    scan = np.concatenate(rows)
    by_k = {
        k: HeldOut(np.concatenate(errors[k]), np.concatenate(oks[k]), scan, n_folds) for k in ks
    }

    def per_weight(totals: np.ndarray) -> dict[float, float]:
        if not scored:
            return {}
        return {float(w): float(v / scored) for w, v in zip(weights, totals, strict=True)}

    return CrossValidation(by_k, per_weight(scores), per_weight(floor_scores), scored)
