"""The HMM's constants chosen by replaying held-out survey walks through it.

A survey walk carries everything a phone sends (WiFi scans, inertial
samples) and where the walker was (its waypoints), so a walk held out of the
radio map is a test of the tracker itself: replayed in one-second batches
with each candidate set of constants, its estimates are scored against the
waypoints. Per-scan scores cannot choose the emission weight: the tracker
multiplies many correlated scans, and how sure each may be depends on how
they combine.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.params import HmmParams
from app.engine.hmm.tracker import HmmTracker
from app.engine.pdr import PdrParams
from app.engine.radiomap import RadioMap, interpolate_waypoints
from app.engine.samples import Batch, ImuSamples, RssiReadings

WRONG_FLOOR_M = 20.0
"""Error (m) an estimate on a wrong floor counts as: worse than most right-floor errors."""

BATCH_MS = 1000
"""Walks are replayed in batches of this much measurement time, as phones upload."""


@dataclass(frozen=True, eq=False)
class HeldWalk:
    """A survey walk as the tracker sees it, with where the walker was.

    Attributes
    ----------
    rssi : RssiReadings
        WiFi readings (site transmitter indices), any order.
    imu : ImuSamples
        Inertial samples, time-ordered.
    waypoints : ndarray, shape (m, 3)
        t (ms), x, y (m).
    floor : int
        Floor index of the walk.
    """

    rssi: RssiReadings
    imu: ImuSamples
    waypoints: np.ndarray
    floor: int


def _batches(walk: HeldWalk) -> list[Batch]:
    """Cut a walk into one-second batches by measurement time."""
    t_all = np.concatenate([walk.rssi.t, walk.imu.t])
    if t_all.size == 0:
        return []
    start = int(t_all.min())
    r_win = (walk.rssi.t - start) // BATCH_MS
    i_win = (walk.imu.t - start) // BATCH_MS
    out = []
    for w in range(int(max(r_win.max(initial=0), i_win.max(initial=0))) + 1):
        r, i = r_win == w, i_win == w
        order = np.argsort(walk.rssi.t[r], kind="stable")
        rssi = RssiReadings(walk.rssi.t[r][order], walk.rssi.tx[r][order], walk.rssi.rssi[r][order])
        imu = ImuSamples(
            walk.imu.t[i], walk.imu.acc[i], walk.imu.gyro[i], walk.imu.mag[i], walk.imu.rot[i]
        )
        out.append(Batch(rssi=rssi, imu=imu))
    return out


def walk_error(model: EmissionModel, params: HmmParams, pdr: PdrParams, walk: HeldWalk) -> float:
    """Return the mean error (m) of one walk's estimates inside its waypoints' span.

    An estimate on a wrong floor counts as ``WRONG_FLOOR_M``; NaN without estimates.
    """
    tracker = HmmTracker(model, params, pdr)
    estimates = [e for b in _batches(walk) for e in tracker.process(b)]
    if not estimates:
        return float("nan")
    t = np.array([e.t for e in estimates], dtype=np.int64)
    truth, inside = interpolate_waypoints(t, walk.waypoints)
    if not inside.any():
        return float("nan")
    xy = np.array([[e.x, e.y] for e in estimates])[inside]
    floor_ok = np.array([e.floor == walk.floor for e in estimates])[inside]
    err = np.hypot(*(xy - truth[inside]).T)
    return float(np.mean(np.where(floor_ok, err, WRONG_FLOOR_M)))


def candidate_errors(
    maps: Sequence[RadioMap],
    walks: Sequence[HeldWalk],
    candidates: Sequence[HmmParams],
    pdr: PdrParams,
) -> np.ndarray:
    """Return the summed walk errors (m) and walks scored per candidate, shape (C, 2)."""
    out = np.zeros((len(candidates), 2))
    for c, params in enumerate(candidates):
        model = EmissionModel(maps, params)
        for walk in walks:
            e = walk_error(model, params, pdr, walk)
            if np.isfinite(e):
                out[c] += (e, 1.0)
    return out
