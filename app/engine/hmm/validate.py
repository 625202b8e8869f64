"""The HMM's constants chosen by replaying held-out survey walks through it.

A survey walk carries everything a phone sends (WiFi scans, inertial
samples) and where the walker was (its waypoints), so a walk held out of the
radio map is a test of the tracker itself: replayed in one-second batches
with each candidate set of constants, its estimates are scored against the
waypoints. Per-scan scores cannot choose the emission weight: the tracker
multiplies many correlated scans, and how sure each may be depends on how
they combine. The same replays, smoothed, choose how far the smoothers may
trust the tracker's positions against its steps.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.params import HmmParams
from app.engine.hmm.tracker import HmmTracker
from app.engine.pdr import PdrParams
from app.engine.plan import FloorPlan
from app.engine.radiomap import RadioMap, interpolate_waypoints
from app.engine.samples import Batch, Estimate, ImuSamples, RssiReadings
from app.engine.smoothing import SmootherParams, fixed_lag, smooth_track

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


@dataclass(frozen=True, eq=False)
class WalkResult:
    """One held-out walk replayed.

    ``score`` is its mean error (m, wrong floors counted as ``WRONG_FLOOR_M``);
    ``error`` and ``radius`` are each right-floor estimate's error and 68%
    radius (m); ``estimates`` what the tracker emitted, for the smoothers.
    """

    score: float
    error: np.ndarray
    radius: np.ndarray
    walk: HeldWalk
    estimates: tuple[Estimate, ...]


def replay_walk(
    model: EmissionModel, params: HmmParams, pdr: PdrParams, walk: HeldWalk
) -> WalkResult | None:
    """Replay one walk; score it by the mean error of its estimates inside the waypoints' span.

    An estimate on a wrong floor counts as ``WRONG_FLOOR_M``; None without estimates.
    """
    tracker = HmmTracker(model, params, pdr)
    return score_walk(walk, [e for b in _batches(walk) for e in tracker.process(b)])


def score_walk(walk: HeldWalk, estimates: Sequence[Estimate]) -> WalkResult | None:
    """Score a walk's estimates against its waypoints; None if none falls inside their span."""
    if not estimates:
        return None
    t = np.array([e.t for e in estimates], dtype=np.int64)
    truth, inside = interpolate_waypoints(t, walk.waypoints)
    if not inside.any():
        return None
    xy = np.array([[e.x, e.y] for e in estimates])[inside]
    floor_ok = np.array([e.floor == walk.floor for e in estimates])[inside]
    radius = np.array([e.accuracy for e in estimates])[inside]
    err = np.hypot(*(xy - truth[inside]).T)
    score = float(np.mean(np.where(floor_ok, err, WRONG_FLOOR_M)))
    return WalkResult(score, err[floor_ok], radius[floor_ok], walk, tuple(estimates))


def candidate_results(
    maps: Sequence[RadioMap],
    walks: Sequence[HeldWalk],
    candidates: Sequence[HmmParams],
    pdr: PdrParams,
    plans: Mapping[int, FloorPlan] | None = None,
) -> list[list[WalkResult]]:
    """Return every replayed walk's result, per candidate, the same walks for each.

    ``plans`` (floor index to plan) let the points reach past the survey, as
    the worker's HMM does.

    A walk one candidate gave no estimate on is left out of all, so candidates
    compare walk by walk.
    """
    out: list[list[WalkResult | None]] = []
    for params in candidates:
        model = EmissionModel(maps, params, plans)
        out.append([replay_walk(model, params, pdr, walk) for walk in walks])
    scored = [all(results[i] is not None for results in out) for i in range(len(walks))]
    return [
        [r for r, ok in zip(results, scored, strict=True) if ok and r is not None]
        for results in out
    ]


def calibrate_radius(
    error: np.ndarray, radius: np.ndarray, min_radius: float, coverage: float = 0.68
) -> tuple[float, float]:
    """Return the radius scale and floor that make the radius hold ``coverage`` of the errors.

    The reported radius is ``max(r_min, sqrt((s r)² + f²))``. A radius that
    holds more shrinks (s < 1, f = 0); one that holds less gets a floor
    (s = 1, f > 0). Both keep the radii's order, so how well the radius ranks
    the errors is unchanged. Found by bisection: coverage grows with s and
    with f. (1, 0) without errors.
    """

    def held(s: float, f: float) -> float:
        return float(np.mean(error <= np.maximum(min_radius, np.hypot(s * radius, f))))

    if error.size == 0:
        return 1.0, 0.0
    if held(1.0, 0.0) >= coverage:
        lo, hi = 0.0, 1.0
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if held(mid, 0.0) >= coverage else (mid, hi)
        return hi, 0.0
    lo, hi = 0.0, float(np.max(error)) + 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if held(1.0, mid) >= coverage else (mid, hi)
    return 1.0, hi


def smoother_scores(
    results: Sequence[WalkResult],
    calibration: tuple[float, float],
    min_radius: float,
    scales: Sequence[float],
) -> dict[str, dict[float, list[float]]]:
    """Return each walk's score under the fixed-lag and the full-pass smoother, per fix scale.

    The replays ran without the radius's calibration; the smoothers weigh
    positions by the radius the server reports, so ``calibration`` (scale,
    floor) is applied first, as the tracker applies it.
    """
    s, f = calibration

    def calibrated(e: Estimate) -> Estimate:
        # r' = max(r_min, sqrt((s r)² + f²))
        return replace(e, accuracy=max(min_radius, float(np.hypot(s * e.accuracy, f))))

    tracks = [[calibrated(e) for e in r.estimates] for r in results]
    out: dict[str, dict[float, list[float]]] = {"fixed_lag": {}, "full_pass": {}}
    for scale in scales:
        params = SmootherParams(fix_scale=scale)
        for name, smooth in (("fixed_lag", fixed_lag), ("full_pass", smooth_track)):
            scored = [
                score_walk(r.walk, smooth(track, params))
                for r, track in zip(results, tracks, strict=True)
            ]
            out[name][scale] = [x.score for x in scored if x is not None]
    return out
