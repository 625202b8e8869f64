"""The forward filter over floors: a hidden Markov model whose state is the floor.

Per positioning window the belief is carried by a sticky transition (a
change of floor has probability ``switch_prob`` per window) and multiplied by
how well the window's readings fit each floor (``evidence.FloorEvidence``);
the floor is the belief's argmax. A single contrary window cannot outweigh a
belief built over many windows, while a real change of floor, whose every
scan favours the new floor, wins within a few scans: the filter needs no
separate hysteresis.

A barometer shapes the transition: a height change of at least
``climb_min_m`` within ``climb_window_ms`` raises the probability of moving
to the floors in that direction to ``climb_switch_prob``; a flat barometer
lowers the probability of any change to ``flat_switch_prob``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from app.engine.floors.params import FloorParams
from app.engine.floors.pressure import PressureHistory
from app.engine.floors.window import NEVER, FloorWindow


def transition_matrix(
    levels: np.ndarray, switch_prob: float, climb_m: float, climb_prob: float, climb_min_m: float
) -> np.ndarray:
    """Return T (F, F) with T[g, f] = P(floor f | floor g one window earlier).

    Parameters
    ----------
    levels : ndarray of int, shape (F,)
        Storey of each floor.
    switch_prob : float
        Probability of a change, shared evenly by the other floors.
    climb_m : float
        Height change (m) the barometer shows (0 without one); at least
        ``climb_min_m`` up or down gives the floors in that direction
        ``climb_prob`` between them, and the others ``switch_prob`` between them.
    """
    levels = np.asarray(levels)
    n = levels.size
    if n == 1:
        return np.ones((1, 1))
    other = ~np.eye(n, dtype=bool)
    # T_gf = ε / (F - 1) for f ≠ g
    T = np.where(other, switch_prob / (n - 1), 0.0)
    if abs(climb_m) >= climb_min_m:
        towards = np.sign(levels[None, :] - levels[:, None]) == np.sign(climb_m)
        n_towards = towards.sum(axis=1, keepdims=True)
        n_rest = (other & ~towards).sum(axis=1, keepdims=True)
        # T_gf = ε_climb / |towards(g)| towards the climb, ε / |rest(g)| elsewhere
        T = np.where(towards, climb_prob / np.maximum(n_towards, 1), 0.0) + np.where(
            other & ~towards, switch_prob / np.maximum(n_rest, 1), 0.0
        )
    # T_gg = 1 - Σ_{f≠g} T_gf
    T[np.arange(n), np.arange(n)] = 1.0 - T.sum(axis=1)
    return T


def forward_step(belief: np.ndarray, T: np.ndarray, windows: int, loglik: np.ndarray) -> np.ndarray:
    """Return the belief after ``windows`` transitions and one window's evidence.

    Parameters
    ----------
    belief : ndarray, shape (F,)
        P(floor) after the previous window.
    T : ndarray, shape (F, F)
        One window's transition (``transition_matrix``).
    windows : int
        Windows elapsed since the previous one (≥ 1).
    loglik : ndarray, shape (F,)
        ln p(readings | floor), up to a constant.
    """
    # π = b Tⁿ
    windows = max(int(windows), 1)
    prior = belief @ (T if windows == 1 else np.linalg.matrix_power(T, windows))
    # b' ∝ π ⊙ exp(ln L - max ln L)
    post = prior * np.exp(loglik - np.max(loglik))
    total = post.sum()
    return post / total if total > 0 else np.full(belief.size, 1.0 / belief.size)


class FloorFilter:
    """Forward filter over one device's floor.

    Parameters
    ----------
    levels : ndarray of int, shape (F,)
        Storey of each floor of the site.
    params : FloorParams
    state : dict, optional
        A :meth:`snapshot` to resume from.
    """

    uses_evidence: ClassVar[bool] = True
    """The belief is updated with the window's ``loglik``."""

    def __init__(
        self, levels: np.ndarray, params: FloorParams, state: dict[str, Any] | None = None
    ) -> None:
        self.levels = np.asarray(levels, dtype=np.int64)
        self.params = params
        n = self.levels.size
        size = params.history_ms // params.window_ms + 1
        state = state or {}
        self.belief = np.asarray(state.get("belief", np.full(n, 1.0 / max(n, 1))), float).copy()
        self.last_t = int(state.get("last_t", NEVER))
        self.t = np.asarray(state.get("t", np.full(size, NEVER)), dtype=np.int64).copy()
        self.heard = np.asarray(state.get("heard", np.zeros((size, n))), float).copy()
        self.pos = int(state.get("pos", 0))
        self.pressure = PressureHistory(state)
        self.current = int(state.get("current", -1))
        self._flat_T: dict[float, np.ndarray] = {}

    def snapshot(self) -> dict[str, Any]:
        """Return the belief, the recently heard floors and the pressure history."""
        return {
            "belief": self.belief.copy(),
            "last_t": self.last_t,
            "t": self.t.copy(),
            "heard": self.heard.copy(),
            "pos": self.pos,
            **self.pressure.snapshot(),
            "current": self.current,
        }

    def _transition(self, eps: float, climb: float) -> np.ndarray:
        """Return ``transition_matrix`` for this window; kept per ε while nothing is climbed."""
        p = self.params
        if abs(climb) >= p.climb_min_m:
            return transition_matrix(self.levels, eps, climb, p.climb_switch_prob, p.climb_min_m)
        T = self._flat_T.get(eps)
        if T is None:
            T = transition_matrix(self.levels, eps, 0.0, p.climb_switch_prob, p.climb_min_m)
            self._flat_T[eps] = T
        return T

    def update(self, window: FloorWindow) -> np.ndarray:
        """Add one window and return the active floors, the chosen floor first.

        The window's ``loglik`` is its evidence (none: the transition alone); a
        floor is active when its transmitters were heard within ``history_ms``.

        Returns
        -------
        ndarray of int
            The chosen floor, then the other active floors by decreasing
            belief; empty when no floor was heard within ``history_ms``.
        """
        p = self.params
        t, n = window.t, self.levels.size
        loglik = np.zeros(n) if window.loglik is None else window.loglik
        heard = np.bincount(np.asarray(window.floor, np.intp), minlength=n)
        barometer, climb = self.pressure.update(t, window.pressure_hpa, p)
        # with a barometer, floors change only in the direction of a climb
        eps = p.flat_switch_prob if barometer else p.switch_prob
        T = self._transition(eps, climb)
        # windows since the previous update: a gap lets the belief relax towards uniform
        windows = 1 if self.last_t == NEVER else max((t - self.last_t) // p.window_ms, 1)
        self.belief = forward_step(self.belief, T, windows, loglik)
        self.last_t = t
        self.t[self.pos] = t
        self.heard[self.pos] = heard
        self.pos = (self.pos + 1) % self.t.size
        active = np.flatnonzero(self.heard[self.t > t - p.history_ms].sum(axis=0) > 0)
        if active.size == 0:
            self.current = -1
            return active
        self.current = int(np.argmax(self.belief))
        rest = active[active != self.current]
        rest = rest[np.argsort(-self.belief[rest], kind="stable")]
        return np.concatenate([[self.current], rest]).astype(np.intp)
