"""The plain per-scan k-NN on the same walk split: the bar any tracker must clear.

Every training walk's scans are reference fingerprints at their surveyed
positions (``app.engine.scan_knn``); every scan of a held-out walk is located
on its own, with no motion model and no memory, and scored like the
server's positions. A tracker that does worse than this on a building has
learnt something wrong about it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from app.datasets.ilc import Walk, fresh_wifi
from app.engine.radiomap import Survey, locate_scans
from app.engine.samples import Estimate, RssiReadings
from app.engine.scan_knn import ReferenceScans, ScanKnnParams
from app.engine.scans import ScanParams, scan_ids
from app.engine.wknn import unique_readings
from app.evaluation.ilc.score import WalkScore, score_walk

MAX_AGE_MS = 2000
"""Readings heard longer than this before their scan are left out: a fixed baseline, apart
from the age the site's build chooses for its own engines."""


def _readings(walk: Walk, index: dict[str, int]) -> RssiReadings:
    """Return the walk's fresh readings of indexed transmitters, timed by their scan."""
    scan = fresh_wifi(walk.wifi, MAX_AGE_MS)
    tx = np.array([index.get(b, -1) for b in scan.bssid.tolist()], dtype=np.int64)
    known = tx >= 0
    return RssiReadings(
        t=scan.t[known].astype(np.int64), tx=tx[known].astype(np.int32), rssi=scan.rssi[known]
    )


def scan_estimates(refs: ReferenceScans, readings: RssiReadings) -> list[Estimate]:
    """Locate every scan of ``readings`` on its own (no motion model, no memory)."""
    scan = scan_ids(readings.t, readings.tx, ScanParams())
    out = []
    for s in np.unique(scan):
        on = scan == s
        tx, rssi = unique_readings(readings.tx[on], readings.rssi[on])
        fix = refs.locate(tx, rssi)
        if fix is None:
            continue
        out.append(
            Estimate(
                t=int(readings.t[on].max()),
                x=float(fix.xy[0]),
                y=float(fix.xy[1]),
                z=0.0,
                floor=fix.floor,
                heading=float("nan"),
                accuracy=float("nan"),
                speed=float("nan"),
                method="knn",
            )
        )
    return out


def scan_knn_scores(
    floors: Sequence[str],
    train: Sequence[Walk],
    test: Sequence[Walk],
    params: ScanKnnParams | None = None,
) -> list[WalkScore]:
    """Score per-scan k-NN on ``test`` with ``train``'s scans as references, one score a walk."""
    ids = sorted({b for w in train for b in fresh_wifi(w.wifi, MAX_AGE_MS).bssid.tolist()})
    index = {b: i for i, b in enumerate(ids)}
    parts = [
        locate_scans(_readings(w, index), w.waypoints, floor=floors.index(w.floor), walk=i)
        for i, w in enumerate(train)
        if w.waypoints.shape[0] >= 2
    ]
    refs = ReferenceScans(Survey.concat(parts), len(ids), params)
    return [
        score_walk(w.waypoints, floors.index(w.floor), scan_estimates(refs, _readings(w, index)))
        for w in test
    ]
