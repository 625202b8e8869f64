"""Floor selection of Eurasian patent 047000, with hysteresis and barometer evidence.

Per floor L the patent accumulates, over the last N seconds, the number n of
readings from transmitters on L, their summed RSSI and their summed A, and
ranks the floors with readings ("active floors") by

    E_L = -n² / Σ rssi_i - n / Σ A_i,

i.e. n / |mean RSSI| + 1 / |mean A|: more and stronger readings win.

Ranking alone flickers where the floors are coupled (atria, stairwells,
glass floors): the first two floors often swap for single windows, and each
swap moves the output to another floor's particle filter. So the first
floor becomes *the* floor only after it has led by a relative margin for
several consecutive windows. A barometer, when the device has one, decides
the ambiguous cases: air pressure falls about 0.12 hPa per metre climbed, so a
change of a storey shows within seconds of taking the stairs or a lift,
while radio needs the old floor's readings to age out of the history. A
pressure change of at least ``climb_min_m`` within ``climb_window_ms`` in the
direction of the challenger switches at once; a flat barometer makes radio
wait ``flat_dwell_windows`` instead. Pressure is compared only across that
short window because weather drifts it by about 1 hPa in three hours.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class FloorParams:
    """Constants of floor selection.

    Attributes
    ----------
    history_ms : int
        N of the patent (its value is not given): readings of the last
        ``history_ms`` count. 10 s spans three to five WiFi scans of a phone.
    window_ms : int
        Length of one positioning window (T_u), the unit of the dwell counts.
    switch_margin : float
        A challenger must score at least (1 + margin) times the current floor.
    dwell_windows : int
        Consecutive windows a challenger must lead before it becomes the floor.
    flat_dwell_windows : int
        The same when a barometer reports no climb.
    hpa_per_m : float
        Pressure drop (hPa) per metre of height near sea level: ρ g = 1.2 kg/m³ × 9.81 m/s².
    climb_min_m : float
        Height change (m) that counts as a change of floor: half a low storey.
    climb_window_ms : int
        Span (ms) over which pressure is compared: long enough for a flight of
        stairs or a lift ride, short against weather drift.
    """

    history_ms: int = 10_000
    window_ms: int = 1000
    switch_margin: float = 0.05
    dwell_windows: int = 3
    flat_dwell_windows: int = 10
    hpa_per_m: float = 0.118
    climb_min_m: float = 2.0
    climb_window_ms: int = 30_000


def window_sums(
    floor: np.ndarray, rssi: np.ndarray, A: np.ndarray, n_floors: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return per-floor (count, Σ rssi, Σ A) of one window's readings.

    Parameters
    ----------
    floor : ndarray of int, shape (n,)
        Floor index of each reading's transmitter.
    rssi, A : ndarray, shape (n,)
        Reading (dBm) and its transmitter's A (dBm).
    """
    floor = np.asarray(floor, dtype=np.intp)
    count = np.bincount(floor, minlength=n_floors).astype(float)
    sum_rssi = np.bincount(floor, weights=rssi, minlength=n_floors)
    sum_a = np.bincount(floor, weights=A, minlength=n_floors)
    return count, sum_rssi, sum_a


def floor_scores(count: np.ndarray, sum_rssi: np.ndarray, sum_a: np.ndarray) -> np.ndarray:
    """Return E_L per floor; NaN for floors without readings (inactive).

    Parameters
    ----------
    count, sum_rssi, sum_a : ndarray, shape (F,)
        n, Σ rssi_i (dBm) and Σ A_i (dBm) per floor over the history.
    """
    active = count > 0
    e = np.full(count.shape, np.nan)
    # E_L = -n² / Σ rssi - n / Σ A
    np.subtract(
        np.divide(-(count * count), sum_rssi, where=active, out=np.zeros(count.shape)),
        np.divide(count, sum_a, where=active, out=np.zeros(count.shape)),
        where=active,
        out=e,
    )
    return e


def rank_floors(scores: np.ndarray) -> np.ndarray:
    """Return the active floors (finite score) by decreasing score; ties by floor index."""
    active = np.flatnonzero(np.isfinite(scores))
    order = np.argsort(-scores[active], kind="stable")
    return active[order]


def pressure_climb(
    t: np.ndarray, hpa: np.ndarray, now: int, params: FloorParams
) -> tuple[bool, float]:
    """Return (barometer present, metres climbed) over the last ``climb_window_ms``.

    Parameters
    ----------
    t, hpa : ndarray, shape (k,)
        Times (ms, increasing) and mean pressure (hPa) of recent windows.
    now : int
        Current time (ms).
    """
    recent = t >= now - params.climb_window_ms
    if recent.sum() < 2:
        return bool(recent.any()), 0.0
    p = hpa[recent]
    # Δh = -(p_now - p_then) / (dp/dh)
    return True, float(-(p[-1] - p[0]) / params.hpa_per_m)


def choose_floor(
    ranking: np.ndarray,
    scores: np.ndarray,
    levels: np.ndarray,
    current: int,
    candidate: int,
    lead: int,
    barometer: bool,
    climb_m: float,
    params: FloorParams,
) -> tuple[int, int, int]:
    """Apply hysteresis to the ranking.

    Parameters
    ----------
    ranking : ndarray of int
        Active floors by decreasing score (``rank_floors``).
    scores : ndarray, shape (F,)
        E_L per floor.
    levels : ndarray of int, shape (F,)
        Storey of each floor (0 ground, -1 first basement).
    current, candidate : int
        The floor now chosen and the challenger being timed (-1 for none).
    lead : int
        Consecutive windows the candidate has led so far.
    barometer : bool
        Whether pressure readings are present.
    climb_m : float
        Height change (m) over the climb window.

    Returns
    -------
    floor, candidate, lead
        The chosen floor (-1 when no floor is active) and the updated challenger state.
    """
    if ranking.size == 0:
        return -1, -1, 0
    best = int(ranking[0])
    if current < 0 or not np.isfinite(scores[current]):
        return best, -1, 0
    if best == current or scores[best] < (1.0 + params.switch_margin) * scores[current]:
        return current, -1, 0
    lead = lead + 1 if best == candidate else 1
    climbing = abs(climb_m) >= params.climb_min_m
    towards = np.sign(levels[best] - levels[current]) == np.sign(climb_m)
    if barometer and climbing and towards:
        return best, -1, 0
    need = params.flat_dwell_windows if barometer and not climbing else params.dwell_windows
    if lead >= need:
        return best, -1, 0
    return current, best, lead


class FloorSelector:
    """Stateful floor selection over a device's windows.

    The per-window sums live in a ring of ``history_ms / window_ms + 1``
    windows; entries older than the history are masked out by their time.

    Parameters
    ----------
    levels : ndarray of int, shape (F,)
        Storey of each floor of the site.
    params : FloorParams
    state : dict, optional
        A :meth:`snapshot` to resume from.
    """

    def __init__(
        self, levels: np.ndarray, params: FloorParams, state: dict[str, Any] | None = None
    ) -> None:
        self.levels = np.asarray(levels, dtype=np.int64)
        self.params = params
        size = params.history_ms // params.window_ms + 1
        n_floors = self.levels.size
        state = state or {}
        never = np.iinfo(np.int64).min // 2
        self.t = np.asarray(state.get("t", np.full(size, never)), dtype=np.int64).copy()
        self.sums = np.asarray(state.get("sums", np.zeros((size, 3, n_floors))), float).copy()
        self.pos = int(state.get("pos", 0))
        self.p_t = np.asarray(state.get("p_t", np.zeros(0, np.int64)), dtype=np.int64)
        self.p_hpa = np.asarray(state.get("p_hpa", np.zeros(0)), dtype=float)
        self.current = int(state.get("current", -1))
        self.candidate = int(state.get("candidate", -1))
        self.lead = int(state.get("lead", 0))

    def snapshot(self) -> dict[str, Any]:
        """Return the accumulators and hysteresis state."""
        return {
            "t": self.t.copy(),
            "sums": self.sums.copy(),
            "pos": self.pos,
            "p_t": self.p_t,
            "p_hpa": self.p_hpa,
            "current": self.current,
            "candidate": self.candidate,
            "lead": self.lead,
        }

    def update(
        self,
        t: int,
        floor: np.ndarray,
        rssi: np.ndarray,
        A: np.ndarray,
        pressure_hpa: np.ndarray | None = None,
    ) -> np.ndarray:
        """Add one window's readings and return the active floors, the chosen floor first.

        Parameters
        ----------
        t : int
            Window time (ms), increasing from call to call.
        floor, rssi, A : ndarray, shape (n,)
            Floor of each reading's transmitter, the reading (dBm) and the
            transmitter's A (dBm); readings with NaN A are ignored.
        pressure_hpa : ndarray, optional
            Barometer readings (hPa) of the window.

        Returns
        -------
        ndarray of int
            Empty when no floor has readings in the history.
        """
        p = self.params
        known = np.isfinite(A) & np.isfinite(rssi)
        sums = window_sums(floor[known], rssi[known], A[known], self.levels.size)
        self.t[self.pos] = t
        self.sums[self.pos] = sums
        self.pos = (self.pos + 1) % self.t.size
        if pressure_hpa is not None and len(pressure_hpa):
            self.p_t = np.append(self.p_t, t)
            self.p_hpa = np.append(self.p_hpa, float(np.mean(pressure_hpa)))
        if self.p_t.size:
            recent = self.p_t >= t - p.climb_window_ms
            self.p_t, self.p_hpa = self.p_t[recent], self.p_hpa[recent]
        count, sum_rssi, sum_a = self.sums[self.t > t - p.history_ms].sum(axis=0)
        scores = floor_scores(count, sum_rssi, sum_a)
        ranking = rank_floors(scores)
        barometer, climb = pressure_climb(self.p_t, self.p_hpa, t, p)
        self.current, self.candidate, self.lead = choose_floor(
            ranking,
            scores,
            self.levels,
            self.current,
            self.candidate,
            self.lead,
            barometer,
            climb,
            p,
        )
        if self.current < 0 or ranking[0] == self.current:
            return ranking
        return np.concatenate([[self.current], ranking[ranking != self.current]]).astype(np.intp)
