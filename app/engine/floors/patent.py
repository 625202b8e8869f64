"""The floor selection of Eurasian patent 047000: E_L ranking with hysteresis.

Per floor L over the last N seconds the selector accumulates the number n of
readings from transmitters on L, their summed RSSI and their summed A, and
ranks the floors with readings ("active floors") by

    E_L = -n² / Σ rssi_i - n / Σ A_i,

i.e. n / |mean RSSI| + 1 / |mean A|: more and stronger readings win.
Ranking alone flickers where the floors are coupled (atria, stairwells,
glass floors), so the first floor becomes *the* floor only after it has led
by a relative margin for several consecutive windows; a climb in the
challenger's direction switches at once, a flat barometer makes radio wait
``flat_dwell_windows`` instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from app.engine.floors.params import FloorParams
from app.engine.floors.pressure import PressureHistory
from app.engine.floors.window import NEVER, FloorWindow


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


class PatentFloorSelector:
    """The patent's floor selection over one device's windows.

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

    uses_evidence: ClassVar[bool] = False
    """E_L is computed from the readings alone."""

    def __init__(
        self, levels: np.ndarray, params: FloorParams, state: dict[str, Any] | None = None
    ) -> None:
        self.levels = np.asarray(levels, dtype=np.int64)
        self.params = params
        size = params.history_ms // params.window_ms + 1
        n_floors = self.levels.size
        state = state or {}
        self.t = np.asarray(state.get("t", np.full(size, NEVER)), dtype=np.int64).copy()
        self.sums = np.asarray(state.get("sums", np.zeros((size, 3, n_floors))), float).copy()
        self.pos = int(state.get("pos", 0))
        self.pressure = PressureHistory(state)
        self.current = int(state.get("current", -1))
        self.candidate = int(state.get("candidate", -1))
        self.lead = int(state.get("lead", 0))

    def snapshot(self) -> dict[str, Any]:
        """Return the accumulators and hysteresis state."""
        return {
            "t": self.t.copy(),
            "sums": self.sums.copy(),
            "pos": self.pos,
            **self.pressure.snapshot(),
            "current": self.current,
            "candidate": self.candidate,
            "lead": self.lead,
        }

    @classmethod
    def update_many(
        cls, selectors: Sequence[PatentFloorSelector], windows: Sequence[FloorWindow]
    ) -> list[np.ndarray]:
        """:meth:`update` for many devices, one after another."""
        return [s.update(w) for s, w in zip(selectors, windows, strict=True)]

    def update(self, window: FloorWindow) -> np.ndarray:
        """Add one window's readings and return the active floors, the chosen floor first.

        Readings whose transmitter has no A (NaN) are ignored.

        Returns
        -------
        ndarray of int
            Empty when no floor has readings in the history.
        """
        p = self.params
        t, floor, rssi, A = window.t, window.floor, window.rssi, window.A
        known = np.isfinite(A) & np.isfinite(rssi)
        sums = window_sums(floor[known], rssi[known], A[known], self.levels.size)
        self.t[self.pos] = t
        self.sums[self.pos] = sums
        self.pos = (self.pos + 1) % self.t.size
        barometer, climb = self.pressure.update(t, window.pressure_hpa, p)
        count, sum_rssi, sum_a = self.sums[self.t > t - p.history_ms].sum(axis=0)
        scores = floor_scores(count, sum_rssi, sum_a)
        ranking = rank_floors(scores)
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
