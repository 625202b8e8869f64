"""Positions refined by what came after them: a least-squares smoother over fixes and steps.

A filter's position at time t knows only the measurements up to t. Weighed
against the device's own motion, the positions that follow can correct it:
the track p minimising

    Σ_i |p_i - z_i|² / σ_i²  +  Σ_i |p_{i+1} - p_i - Δo_i|² / m_i²

where z_i are the filter's positions with their standard deviation σ_i
(from the 68% radius, times ``fix_scale``), Δo_i the displacement the steps
measured between them (odometry) and m_i = a + b Δt_i its error, growing with
the time between the two (a walker's step length and heading drift). Without
odometry between two positions (no steps counted) the walker may have moved
anywhere a walking speed allows. The normal equations are tridiagonal, solved
by elimination in one compiled pass. Following the strongest smartphone pipelines on
this data format (PHONES.md: fix weight ≈ 1/8², motion weight ≈
1/(0.3 + 0.3 Δt)²).

``smooth_track`` solves a whole stored track (the full backward pass);
``fixed_lag`` gives, for each position, what a smoother ``lag_ms`` behind it
says: the live stream's refined re-emission.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from numba import njit

from app.engine.gaussian import R68_SIGMAS_2D
from app.engine.samples import Estimate


@dataclass(frozen=True)
class SmootherParams:
    """Tunable constants of the smoother.

    Attributes
    ----------
    lag_ms : int
        A fixed-lag position is solved with the positions up to this much
        later (the refined stream runs this far behind measurement time):
        the 5 s a dashboard may wait; the longer the lag, the more later
        positions refine it, but only a little beyond a few seconds.
    window_ms : int
        A fixed-lag solve uses the positions of this much time before the
        one it refines (older ones no longer move it).
    fix_floor_m : float
        No filter position is trusted to better than this (m, one σ).
    fix_scale : float
        Factor on each position's σ (its 68% radius over the 2-D 68%
        quantile). A filter's positions are not independent fixes: each
        already carries the scans before it, so weighing them as if they were
        counts the same evidence many times and pulls the track onto the
        filter's own errors. A site's radio-map build chooses it on replayed
        held-out walks, apart for the fixed lag and the full pass.
    motion_std_m : float
        a: error (m) of any odometry displacement, however short.
    motion_std_per_s : float
        b: error (m) added per second between two positions.
    free_speed_mps : float
        Without odometry between two positions, the walker moved at most
        about this fast (m/s) in any direction.
    """

    lag_ms: int = 5000
    window_ms: int = 30_000
    fix_floor_m: float = 1.0
    fix_scale: float = 1.0
    motion_std_m: float = 0.3
    motion_std_per_s: float = 0.3
    free_speed_mps: float = 1.5


def smooth_positions(
    t: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
    odometry: np.ndarray,
    params: SmootherParams,
) -> np.ndarray:
    """Return the least-squares track of one floor's positions, shape (n, 2).

    Parameters
    ----------
    t : ndarray of int, shape (n,)
        Times (ms), ascending.
    xy : ndarray, shape (n, 2)
        Filter positions (m).
    sigma : ndarray, shape (n,)
        Their standard deviations (m).
    odometry : ndarray, shape (n, 2)
        Dead-reckoned position at each time (m, any origin); NaN where unknown.
    params : SmootherParams
        Motion and fix errors.
    """
    if t.size < 2:
        return np.asarray(xy, dtype=float).copy()
    return _solve_track(
        np.asarray(t, dtype=np.int64),
        np.asarray(xy, dtype=float),
        np.asarray(sigma, dtype=float),
        np.asarray(odometry, dtype=float),
        _errors(params),
    )


def _errors(params: SmootherParams) -> tuple[float, float, float, float, float]:
    """Return the fix and motion error constants the compiled solvers take, in their order."""
    return (
        float(params.fix_scale),
        float(params.fix_floor_m),
        float(params.motion_std_m),
        float(params.motion_std_per_s),
        float(params.free_speed_mps),
    )


def load_solver() -> None:
    """Smooth a two-position track once, whole and by the fixed lag: solvers compiled early.

    They are ready before a device needs them: the first solve in a process compiles
    them, or reads them from numba's disk cache.
    """
    smooth_positions(
        np.array([0, 1000]), np.zeros((2, 2)), np.ones(2), np.zeros((2, 2)), SmootherParams()
    )
    smoother = FixedLagSmoother(SmootherParams(lag_ms=1000))
    for t in (0, 1000):
        at = Estimate(t, 0.0, 0.0, 0.0, 0, heading=0.0, accuracy=1.0, speed=0.0, method="")
        smoother.push([at])


@njit(cache=True)
def _solve_track(
    t: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
    odometry: np.ndarray,
    errors: tuple[float, float, float, float, float],
) -> np.ndarray:  # pragma: no cover - compiled
    """Build and solve the smoother's tridiagonal normal equations (n ≥ 2).

    A live device solves a few dozen positions several times a second: one
    compiled pass costs a few microseconds where numpy's array calls and the
    banded LAPACK wrapper cost some 40. ``errors`` are ``_errors(params)``.
    """
    fix_scale, fix_floor_m, motion_std_m, motion_std_per_s, free_speed_mps = errors
    n = t.size
    diag = np.empty(n)
    off = np.zeros(n)  # off[i] couples positions i and i + 1
    rhs = np.empty((n, 2))
    for i in range(n):
        # w_fix = 1 / max(s σ, σ_min)²
        sd = max(fix_scale * sigma[i], fix_floor_m)
        w = 1.0 / (sd * sd)
        diag[i] = w
        rhs[i, 0] = w * xy[i, 0]
        rhs[i, 1] = w * xy[i, 1]
    for i in range(n - 1):
        dt = (t[i + 1] - t[i]) / 1000.0
        sx = odometry[i + 1, 0] - odometry[i, 0]
        sy = odometry[i + 1, 1] - odometry[i, 1]
        # m_i = a + b Δt with odometry, v Δt (+ a) without
        if np.isfinite(sx) and np.isfinite(sy):
            m = motion_std_m + motion_std_per_s * dt
        else:
            m = motion_std_m + free_speed_mps * dt
            sx = 0.0
            sy = 0.0
        w = 1.0 / (m * m)
        # (W_fix + Dᵀ W_mot D) p = W_fix z + Dᵀ W_mot Δo, D the difference operator
        diag[i] += w
        diag[i + 1] += w
        off[i] = -w
        rhs[i, 0] -= w * sx
        rhs[i, 1] -= w * sy
        rhs[i + 1, 0] += w * sx
        rhs[i + 1, 1] += w * sy
    # the symmetric positive definite tridiagonal system by elimination (Thomas)
    c = np.empty(n)
    out = np.empty((n, 2))
    c[0] = off[0] / diag[0]
    out[0, 0] = rhs[0, 0] / diag[0]
    out[0, 1] = rhs[0, 1] / diag[0]
    for i in range(1, n):
        denom = diag[i] - off[i - 1] * c[i - 1]
        c[i] = off[i] / denom
        out[i, 0] = (rhs[i, 0] - off[i - 1] * out[i - 1, 0]) / denom
        out[i, 1] = (rhs[i, 1] - off[i - 1] * out[i - 1, 1]) / denom
    for i in range(n - 2, -1, -1):
        out[i, 0] -= c[i] * out[i + 1, 0]
        out[i, 1] -= c[i] * out[i + 1, 1]
    return out


def _arrays(
    estimates: Sequence[Estimate],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    t = np.array([e.t for e in estimates], dtype=np.int64)
    xy = np.array([[e.x, e.y] for e in estimates], dtype=float).reshape(-1, 2)
    sigma = np.array([e.accuracy for e in estimates], dtype=float) / R68_SIGMAS_2D
    sigma = np.where(np.isfinite(sigma), sigma, np.inf)
    odo = np.array(
        [e.odometry if e.odometry is not None else (np.nan, np.nan) for e in estimates],
        dtype=float,
    ).reshape(-1, 2)
    floor = np.array([e.floor for e in estimates], dtype=np.int64)
    return t, xy, sigma, odo, floor


def _runs(floor: np.ndarray) -> list[tuple[int, int]]:
    """Return [start, stop) of each run of equal floors."""
    cuts = np.flatnonzero(np.diff(floor)) + 1
    bounds = np.concatenate([[0], cuts, [floor.size]])
    return list(zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True))


def smooth_track(estimates: Sequence[Estimate], params: SmootherParams) -> list[Estimate]:
    """Return a whole track smoothed, floor run by floor run (the full backward pass)."""
    if not estimates:
        return []
    t, xy, sigma, odo, floor = _arrays(estimates)
    out = xy.copy()
    for lo, hi in _runs(floor):
        out[lo:hi] = smooth_positions(t[lo:hi], xy[lo:hi], sigma[lo:hi], odo[lo:hi], params)
    return [replace(e, x=float(p[0]), y=float(p[1])) for e, p in zip(estimates, out, strict=True)]


def fixed_lag(estimates: Sequence[Estimate], params: SmootherParams) -> list[Estimate]:
    """Return each position as a smoother ``lag_ms`` behind it refines it.

    Position i is solved with the positions of its floor run from
    ``window_ms`` before it to ``lag_ms`` after it: exactly what a live
    smoother holding that lag knows when it re-emits position i.
    """
    if not estimates:
        return []
    t, xy, sigma, odo, floor = _arrays(estimates)
    out = xy.copy()
    for lo, hi in _runs(floor):
        for i in range(lo, hi):
            a = lo + int(np.searchsorted(t[lo:hi], t[i] - params.window_ms, side="left"))
            b = lo + int(np.searchsorted(t[lo:hi], t[i] + params.lag_ms, side="right"))
            solved = smooth_positions(t[a:b], xy[a:b], sigma[a:b], odo[a:b], params)
            out[i] = solved[i - a]
    return [replace(e, x=float(p[0]), y=float(p[1])) for e, p in zip(estimates, out, strict=True)]


class FixedLagSmoother:
    """A device's live smoother: each position re-emitted refined once ``lag_ms`` has passed.

    Holds the positions of the last ``window_ms + lag_ms`` of measurement
    time, with their times, coordinates, σ, odometry and floors as arrays
    kept alongside (each position converted once, not at every solve).
    ``push`` takes the filter's new positions and returns the refined ones
    that are now due (``smoothed`` set), each with one solve, as
    ``fixed_lag`` solves it over a whole track.
    """

    def __init__(self, params: SmootherParams, state: dict[str, Any] | None = None) -> None:
        self.params = params
        self.held: list[Estimate] = []
        self.done_t = -1
        if state is not None:
            self.held = [_estimate(e) for e in json.loads(str(state["held"]))]
            self.done_t = int(state["done_t"])
        self._columns: tuple[np.ndarray, ...] = _arrays(self.held)

    def push(self, estimates: Sequence[Estimate], *, now_t: int | None = None) -> list[Estimate]:
        """Add the filter's new positions; return the refined positions now due, in time order.

        A position is due once the filter has reported positions ``lag_ms``
        after it (or measurement time ``now_t`` has passed that far).
        """
        p = self.params
        last = self.held[-1].t if self.held else -1
        new = []
        for e in estimates:
            if e.t > last:
                new.append(e)
                last = e.t
        if new:
            self.held += new
            self._columns = tuple(
                np.concatenate([old, part])
                for old, part in zip(self._columns, _arrays(new), strict=True)
            )
        if not self.held:
            return []
        t = self._columns[0]
        horizon = max(int(t[-1]), now_t if now_t is not None else -1)
        due = np.flatnonzero((t > self.done_t) & (t <= horizon - p.lag_ms))
        _, xy, sigma, odo, floor = self._columns
        refined = _refine_held(
            due, t, xy, sigma, odo, floor, int(p.window_ms), int(p.lag_ms), _errors(p)
        )
        out = [
            replace(self.held[i], x=float(x), y=float(y), smoothed=True)
            for i, (x, y) in zip(due.tolist(), refined.tolist(), strict=True)
        ]
        if due.size:
            self.done_t = int(t[due[-1]])
        first = int(np.searchsorted(t, self.done_t - p.window_ms, side="left"))
        if first:
            self.held = self.held[first:]
            self._columns = tuple(column[first:] for column in self._columns)
        return out

    def flush(self) -> list[Estimate]:
        """Return every held position not yet refined, refined with what is known (stream end)."""
        if not self.held:
            return []
        last = self.held[-1].t
        return self.push([], now_t=last + self.params.lag_ms)

    def snapshot(self) -> dict[str, Any]:
        """Return the held positions and the last refined time as plain values."""
        return {"held": json.dumps([asdict(e) for e in self.held]), "done_t": self.done_t}


def _estimate(fields: dict[str, Any]) -> Estimate:
    """Return an estimate from its ``asdict`` fields read back from JSON."""
    odometry = fields.get("odometry")
    return Estimate(**(fields | {"odometry": None if odometry is None else tuple(odometry)}))


@njit(cache=True)
def _refine_held(
    due: np.ndarray,
    t: np.ndarray,
    xy: np.ndarray,
    sigma: np.ndarray,
    odometry: np.ndarray,
    floor: np.ndarray,
    window_ms: int,
    lag_ms: int,
    errors: tuple[float, float, float, float, float],
) -> np.ndarray:  # pragma: no cover - compiled
    """Return each due held position solved with its floor run's positions in its window.

    The window of position i reaches ``window_ms`` before it and ``lag_ms``
    after it, and stops where the floor changes; shape (len(due), 2).
    """
    out = np.empty((due.size, 2))
    for n in range(due.size):
        i = due[n]
        lo = np.searchsorted(t, t[i] - window_ms, side="left")
        hi = np.searchsorted(t, t[i] + lag_ms, side="right")
        # only the floor run holding position i
        a = i
        while a > lo and floor[a - 1] == floor[i]:
            a -= 1
        b = i + 1
        while b < hi and floor[b] == floor[i]:
            b += 1
        if b - a < 2:
            out[n] = xy[i]
            continue
        out[n] = _solve_track(t[a:b], xy[a:b], sigma[a:b], odometry[a:b], errors)[i - a]
    return out
