"""How old a WiFi reading may be and still count in its scan, chosen from a site's surveys.

A phone's scan lists every access point it still remembers, each with the
time it was last heard (Android's ``ScanResult.timestamp``). Readings heard
a few seconds before the scan completed add access points the scan itself
missed, at the cost of having been heard a few metres back along the walk;
much older ones describe another place. Where the balance lies depends on
how fast people walk there and how often the phones scan, so a build scores
each candidate age by the per-scan k-NN (``app.engine.scan_knn``) on its own
surveys, whole walks held out in turn, and keeps the age nearest the default
that is as good as the best walk by walk.

On ILC site1's 457 training walks (five walk folds, every other held-out
scan, mean of the walks' mean errors) the k-NN erred 6.774 m with readings
up to 2 s old, 6.161 m at 5 s and 5.978 m at 8 s; a one-off run on two of
those folds found 12 s worse than 6 s (7.29 m against 7.04 m).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from app.engine.radiomap import Survey
from app.engine.scan_knn import ReferenceScans

DEFAULT_MAX_AGE_MS = 5000
"""Oldest last-seen age (ms) a site without a build uses: the strongest published pipelines
on this kind of data dropped readings more than 5 s older than their scan."""

AGE_CANDIDATES_MS = (2000, 3000, 4000, 5000, 6000, 8000)
"""Oldest last-seen age (ms before the scan's time) a build tries."""

WRONG_FLOOR_M = 20.0
"""Error (m) a scan located on a wrong floor counts as."""


def walk_errors(survey: Survey, n_tx: int, folds: int, *, every: int = 2) -> dict[int, float]:
    """Return each walk's mean per-scan k-NN error (m) with its fold's walks held out.

    Walk ``w`` is in fold ``w mod folds``; every ``every``-th scan of a
    held-out walk is located on the other folds' scans. A scan on a wrong
    floor counts as ``WRONG_FLOOR_M``; a scan that shares no transmitter with
    them is not scored.
    """
    walks = np.unique(survey.scan_walk)
    k = min(folds, walks.size)
    if k < 2:
        return {}
    by_scan = np.argsort(survey.reading_scan, kind="stable")
    starts = np.searchsorted(survey.reading_scan[by_scan], np.arange(survey.n_scans + 1))
    errors: dict[int, list[float]] = {}
    fold_of_scan = survey.scan_walk % k
    for fold in range(k):
        held = fold_of_scan == fold
        if held.all() or not held.any():
            continue
        refs = ReferenceScans(survey.select(~held), n_tx)
        for j in np.flatnonzero(held)[::every]:
            rows = by_scan[starts[j] : starts[j + 1]]
            fix = refs.locate(survey.reading_tx[rows], survey.reading_rssi[rows])
            if fix is None:
                continue
            right = fix.floor == survey.scan_floor[j]
            error = float(np.hypot(*(fix.xy - survey.scan_xy[j]))) if right else WRONG_FLOOR_M
            errors.setdefault(int(survey.scan_walk[j]), []).append(error)
    return {w: float(np.mean(e)) for w, e in errors.items()}


def paired_scores(by_age: Mapping[int, Mapping[int, float]]) -> dict[float, list[float]]:
    """Return each age's walk errors over the walks every age scored, in one walk order."""
    common = sorted(set.intersection(*(set(e) for e in by_age.values()))) if by_age else []
    return {float(age): [errors[w] for w in common] for age, errors in by_age.items()}
