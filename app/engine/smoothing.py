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
anywhere a walking speed allows. The normal equations are tridiagonal, one
banded solve per coordinate. Following the strongest smartphone pipelines on
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
from scipy.linalg import solveh_banded

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
        the 5 s a dashboard may wait. On the validation walks of two builds
        (site1, and two of its floors with half the surveys) the refined
        mean went from 5.519 to 5.489 m and from 9.294 to 9.235 m against 4 s.
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
    n = t.size
    if n < 2:
        return np.asarray(xy, dtype=float).copy()
    dt = np.diff(t) / 1000.0
    step = np.diff(odometry, axis=0)
    known = np.all(np.isfinite(step), axis=1)
    # m_i = a + b Δt with odometry, v Δt (+ a) without
    m = np.where(
        known,
        params.motion_std_m + params.motion_std_per_s * dt,
        params.motion_std_m + params.free_speed_mps * dt,
    )
    step = np.where(known[:, None], step, 0.0)
    w_fix = 1.0 / np.maximum(params.fix_scale * sigma, params.fix_floor_m) ** 2
    w_mot = 1.0 / m**2
    # normal equations (W_fix + Dᵀ W_mot D) p = W_fix z + Dᵀ W_mot Δo, D the difference operator
    diag = w_fix.copy()
    diag[:-1] += w_mot
    diag[1:] += w_mot
    upper = np.concatenate([[0.0], -w_mot])
    rhs = w_fix[:, None] * xy
    rhs[:-1] -= w_mot[:, None] * step
    rhs[1:] += w_mot[:, None] * step
    return solveh_banded(np.vstack([upper, diag]), rhs)


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
    time. ``push`` takes the filter's new positions and returns the refined
    ones that are now due (``smoothed`` set), each with one banded solve, as
    ``fixed_lag`` solves it over a whole track.
    """

    def __init__(self, params: SmootherParams, state: dict[str, Any] | None = None) -> None:
        self.params = params
        self.held: list[Estimate] = []
        self.done_t = -1
        if state is not None:
            self.held = [_estimate(e) for e in json.loads(str(state["held"]))]
            self.done_t = int(state["done_t"])

    def push(self, estimates: Sequence[Estimate], *, now_t: int | None = None) -> list[Estimate]:
        """Add the filter's new positions; return the refined positions now due, in time order.

        A position is due once the filter has reported positions ``lag_ms``
        after it (or measurement time ``now_t`` has passed that far).
        """
        p = self.params
        self.held += [e for e in estimates if e.t > (self.held[-1].t if self.held else -1)]
        if not self.held:
            return []
        horizon = max(self.held[-1].t, now_t if now_t is not None else -1)
        due = [i for i, e in enumerate(self.held) if self.done_t < e.t <= horizon - p.lag_ms]
        out = [replace(self._refine(i), smoothed=True) for i in due]
        if due:
            self.done_t = self.held[due[-1]].t
        keep_from = self.done_t - p.window_ms
        self.held = [h for h in self.held if h.t >= keep_from]
        return out

    def _refine(self, i: int) -> Estimate:
        """Return held position i solved with its floor run's positions in its window."""
        p, held, e = self.params, self.held, self.held[i]
        lo, hi = i, i + 1
        while lo > 0 and held[lo - 1].floor == e.floor and held[lo - 1].t >= e.t - p.window_ms:
            lo -= 1
        while hi < len(held) and held[hi].floor == e.floor and held[hi].t <= e.t + p.lag_ms:
            hi += 1
        t, xy, sigma, odo, _ = _arrays(held[lo:hi])
        x, y = smooth_positions(t, xy, sigma, odo, p)[i - lo]
        return replace(e, x=float(x), y=float(y))

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
