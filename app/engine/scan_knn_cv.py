"""The per-scan k-NN cross-validated on a site's own surveys, whole walks held out in turn.

A build scores its per-scan constants here: how old a WiFi reading may be
(``app.engine.wifi_age``); the signal level counted as nothing and what a
transmitter only one scan heard costs, how many neighbours the k-NN
averages, how steeply it weighs them and how much strong transmitters count
(``choose_neighbours``); and how far its fixes fall from the walkers
(``fix_spread``). Walk ``w`` is in fold
``w mod folds``; every ``every``-th scan of a held-out walk is located on the
other folds' scans, and each walk's mean error is one sample, so candidates
are compared walk by walk (``app.engine.tuning.one_standard_error_choice``).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import replace

import numpy as np

from app.engine.radiomap import Survey
from app.engine.scan_knn import LEVEL_POWERS, ReferenceScans, ScanKnnParams
from app.engine.tuning import one_standard_error_choice

WRONG_FLOOR_M = 20.0
"""Error (m) a scan located on a wrong floor counts as."""

K_CANDIDATES = (5, 10, 15, 20)
"""Neighbours averaged that a build tries."""

POWER_CANDIDATES = (2.0, 3.0, 4.0, 6.0, 8.0)
"""Exponents of the neighbour weights ``(d / d_min)^-p`` a build tries."""

FLOOR_CANDIDATES_DBM = (-100.0, -95.0, -90.0, -85.0, -80.0, -75.0)
"""Signal levels counted as nothing (``ScanKnnParams.floor_dbm``) a build tries: where
readings near a phone's sensitivity say more noise than place depends on the
phones and on how densely the access points stand."""

PENALTY_CANDIDATES = (25.0, 50.0, 100.0)
"""Distances (dB) for two scans sharing nothing (``ScanKnnParams.unshared_penalty``) a
build tries."""

PairErrors = dict[tuple[int, float], dict[int, float]]
"""Each walk's mean held-out error (m) by (k, weight power)."""


def _held_out(
    survey: Survey, n_tx: int, folds: int, every: int, params: ScanKnnParams
) -> Iterator[tuple[ReferenceScans, int, np.ndarray]]:
    """Yield (other folds' references, scan row, its distances to them) per held-out scan.

    Distances are ``params``'. Every ``every``-th scan of each fold is held
    out in turn; scans sharing no transmitter with the other folds are skipped.
    """
    k = min(folds, np.unique(survey.scan_walk).size)
    if k < 2:
        return
    by_scan = np.argsort(survey.reading_scan, kind="stable")
    starts = np.searchsorted(survey.reading_scan[by_scan], np.arange(survey.n_scans + 1))
    fold_of_scan = survey.scan_walk % k
    for fold in range(k):
        held = fold_of_scan == fold
        if held.all() or not held.any():
            continue
        refs = ReferenceScans(survey.select(~held), n_tx, params)
        for j in np.flatnonzero(held)[::every]:
            rows = by_scan[starts[j] : starts[j + 1]]
            d = refs.distances(survey.reading_tx[rows], survey.reading_rssi[rows])
            if np.isfinite(d).any():
                yield refs, int(j), d


def walk_errors(
    survey: Survey,
    n_tx: int,
    folds: int,
    *,
    every: int = 2,
    variants: Sequence[tuple[int, float]] = (),
    params: ScanKnnParams | None = None,
) -> list[dict[int, float]]:
    """Return each walk's mean held-out per-scan k-NN error (m), one mapping per variant.

    ``variants`` are (k, weight power) pairs located from the same distances
    (``params``', the defaults when None; ``params``' own k and power alone
    when empty). A scan on a wrong floor counts as ``WRONG_FLOOR_M``; a scan
    that shares no transmitter with the other folds is not scored; fewer than
    two folds score nothing.
    """
    base = params or ScanKnnParams()
    pairs = list(variants) or [(base.k, base.weight_power)]
    errors: list[dict[int, list[float]]] = [{} for _ in pairs]
    for refs, j, d in _held_out(survey, n_tx, folds, every, base):
        walk = int(survey.scan_walk[j])
        for v, (n, power) in enumerate(pairs):
            fix = refs.fix(d, n, power)
            assert fix is not None
            right = fix.floor == survey.scan_floor[j]
            error = float(np.hypot(*(fix.xy - survey.scan_xy[j]))) if right else WRONG_FLOOR_M
            errors[v].setdefault(walk, []).append(error)
    return [{w: float(np.mean(e)) for w, e in by_walk.items()} for by_walk in errors]


def fix_spread(
    survey: Survey, n_tx: int, folds: int, params: ScanKnnParams, *, every: int = 2
) -> float | None:
    """Return the root mean square of the held-out per-scan k-NN errors (m) on the right floor.

    How far a scan's k-NN fix lies from the walker on this site, tails
    included: the HMM spreads each neighbour of its k-NN fix by this much
    (``HmmParams.fix_sigma_m``). None when no scan was scored.
    """
    squares = []
    for refs, j, d in _held_out(survey, n_tx, folds, every, params):
        fix = refs.fix(d, params.k, params.weight_power)
        assert fix is not None
        if fix.floor == survey.scan_floor[j]:
            squares.append(float(np.sum((fix.xy - survey.scan_xy[j]) ** 2)))
    return float(np.sqrt(np.mean(squares))) if squares else None


def paired_scores(by_candidate: Mapping[float, Mapping[int, float]]) -> dict[float, list[float]]:
    """Return each candidate's walk errors over the walks every candidate scored, in one order."""
    common = (
        sorted(set.intersection(*(set(e) for e in by_candidate.values()))) if by_candidate else []
    )
    return {float(c): [errors[w] for w in common] for c, errors in by_candidate.items()}


def choose_neighbours(
    survey: Survey, n_tx: int, folds: int
) -> tuple[ScanKnnParams, dict[str, dict[float, list[float]]]]:
    """Return k-NN constants with the site's signal floor, penalty, neighbours and powers.

    The scores returned beside them are every candidate's walk errors, by
    constant. Each constant is chosen in turn, the ones before it at their
    chosen values and the ones after at their defaults: the signal floor,
    then the penalty for what one scan heard alone (both at the default k and
    weight power), the level power, the weight power, and k. Each is the
    candidate nearest the default that is as good as the best walk by walk.

    A build of ILC site1's training walks moves the signal floor and the
    weight power off their defaults, and two of its floors with half the
    surveys move the signal floor and the penalty instead: the distance that
    fits one building does not fit another. ``locus eval ilc`` prints what
    the build chose and its error at every candidate
    (``knn_walk_error_m_by_floor_dbm`` and the like); ``--floors`` and
    ``--train-share`` make the smaller building.
    """
    base = ScanKnnParams()
    default_pair = [(base.k, base.weight_power)]
    pairs = [(base.k, p) for p in POWER_CANDIDATES] + [
        (k, p) for k in K_CANDIDATES if k != base.k for p in POWER_CANDIDATES
    ]
    passes: dict[ScanKnnParams, PairErrors] = {}

    def scored(params: ScanKnnParams, wanted: list[tuple[int, float]]) -> PairErrors:
        # every (k, power) pair from one pass of distances: the distances are the cost
        known = passes.get(params, {})
        if not all(pair in known for pair in wanted):
            errors = walk_errors(survey, n_tx, folds, variants=wanted, params=params)
            passes[params] = known | dict(zip(wanted, errors, strict=True))
        return passes[params]

    def at_default(params: ScanKnnParams) -> dict[int, float]:
        return scored(params, default_pair)[default_pair[0]]

    by_floor = paired_scores(
        {f: at_default(replace(base, floor_dbm=f)) for f in FLOOR_CANDIDATES_DBM}
    )
    if not all(by_floor.values()):
        return base, {}
    chosen = replace(base, floor_dbm=one_standard_error_choice(by_floor, base.floor_dbm))
    by_penalty = paired_scores(
        {c: at_default(replace(chosen, unshared_penalty=c)) for c in PENALTY_CANDIDATES}
    )
    penalty = one_standard_error_choice(by_penalty, base.unshared_penalty)
    chosen = replace(chosen, unshared_penalty=penalty)
    found = {g: scored(replace(chosen, level_power=g), pairs) for g in LEVEL_POWERS}
    by_level = paired_scores({float(g): f[default_pair[0]] for g, f in found.items()})
    level = int(one_standard_error_choice(by_level, base.level_power))
    by_power = paired_scores({p: found[level][(base.k, p)] for p in POWER_CANDIDATES})
    power = one_standard_error_choice(by_power, base.weight_power)
    by_k = paired_scores({float(k): found[level][(k, power)] for k in K_CANDIDATES})
    k = int(one_standard_error_choice(by_k, float(base.k)))
    scores = {
        "floor_dbm": by_floor,
        "unshared_penalty": by_penalty,
        "level_power": by_level,
        "weight_power": by_power,
        "k": by_k,
    }
    return replace(chosen, level_power=level, k=k, weight_power=power), scores
