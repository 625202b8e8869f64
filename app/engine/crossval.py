"""Held-out accuracy of a fingerprint radio map by walk-level cross-validation.

Scans of one survey walk are strongly correlated (same phone, same day, the
same line walked), so holding out single scans would flatter the map: each
held-out scan would sit between two training scans of its own walk. Folds are
therefore whole walks: walk ``w`` is in fold ``w mod k``; each fold's scans are
located by WKNN on maps built from the other folds only, and their errors
pooled.

WKNN is vectorised over the held-out scans: with readings shifted by the
missing level, ``d² = |v|² - 2 S Vᵀ + |s|²`` is one dense matrix product per
floor map for a chunk of scans.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from app.engine.plan import FloorPlan
from app.engine.radiomap import RadioMap, RadioMapParams, Survey, build_radio_map
from app.engine.wknn import Fingerprints, WknnParams

CHUNK = 512
"""Held-out scans located per matrix product (bounds the (scans × points) distance block)."""


@dataclass(frozen=True)
class HeldOut:
    """Errors of every held-out scan located by WKNN.

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


def wknn_scans(
    fingerprints: Fingerprints, survey: Survey, params: WknnParams
) -> tuple[np.ndarray, np.ndarray]:
    """Locate every scan of ``survey`` by WKNN (same answer as ``wknn`` scan by scan).

    Floor by floor, each chunk of scans is densified over the floor's
    transmitters so the distances are one BLAS product, and only the floor's
    k nearest are kept; the k nearest overall are among those.

    Returns
    -------
    xy : ndarray, shape (S, 2)
        Weighted mean position (m) of the neighbours on the voted floor.
    floor : ndarray of int, shape (S,)
        Voted floor index.
    """
    n = survey.n_scans
    # s = max(rssi - missing, 0) per (scan, transmitter)
    s_val = np.maximum(survey.reading_rssi - fingerprints.missing, 0.0)
    n_tx = max(int(survey.reading_tx.max(initial=-1)) + 1, fingerprints.columns[0].size)
    S = sparse.csr_matrix((s_val, (survey.reading_scan, survey.reading_tx)), shape=(n, n_tx))
    s_norm = np.asarray(S.multiply(S).sum(axis=1)).ravel()
    k = params.k
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
    pick = np.argpartition(cand_d, k - 1, axis=1)[:, :k]
    dk = np.take_along_axis(cand_d, pick, axis=1)
    near = np.take_along_axis(cand_i, pick, axis=1)
    # w_i = 1 / (d_i + ε)
    w = 1.0 / (dk + params.eps_db)
    floors = fingerprints.floor[near]
    xy_out = np.zeros((n, 2))
    floor_out = np.zeros(n, dtype=np.int64)
    for r in range(n):
        votes = np.bincount(floors[r], weights=w[r])
        best = int(np.argmax(votes))
        on = floors[r] == best
        # x = Σ w_i x_i / Σ w_i over the voted floor's neighbours
        xy_out[r] = w[r, on] @ fingerprints.xy[near[r, on]] / w[r, on].sum()
        floor_out[r] = best
    return xy_out, floor_out


def cross_validate(
    survey: Survey,
    plans: Mapping[int, FloorPlan],
    params: RadioMapParams,
    wknn_params: WknnParams,
    *,
    folds: int = 5,
    progress: Callable[[float], None] | None = None,
) -> HeldOut | None:
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
    progress : callable, optional
        Called with the fraction of folds done.
    """
    walks = np.unique(survey.scan_walk)
    k = min(folds, walks.size)
    if k < 2:
        return None
    fold_of_scan = survey.scan_walk % k
    errors, oks, rows = [], [], []
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
            held = survey.select(test)
            xy, floor = wknn_scans(Fingerprints(maps, wknn_params.missing_dbm), held, wknn_params)
            # e = |x̂ - x|
            errors.append(np.hypot(*(xy - held.scan_xy).T))
            oks.append(floor == held.scan_floor)
            rows.append(np.flatnonzero(test))
        if progress is not None:
            progress((fold + 1) / k)
    if not errors:
        return None
    return HeldOut(
        error_m=np.concatenate(errors),
        floor_ok=np.concatenate(oks),
        scan=np.concatenate(rows),
        folds=k,
    )
