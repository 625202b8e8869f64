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

import functools
from collections.abc import Sequence
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


def forward_steps(belief: np.ndarray, power: np.ndarray, loglik: np.ndarray) -> np.ndarray:
    """Return the beliefs of many devices after their transitions and one window's evidence.

    Parameters
    ----------
    belief : ndarray, shape (D, F)
        P(floor) of each device after its previous window.
    power : ndarray, shape (D, F, F)
        Each device's transition since then: ``transition_matrix`` to the
        power of the windows elapsed.
    loglik : ndarray, shape (D, F)
        ln p(readings | floor), up to a constant per device.
    """
    # π_f = Σ_g b_g P_gf, summed in g order for every row alike
    prior = (belief[:, :, None] * power).sum(axis=1)
    # b' ∝ π ⊙ exp(ln L - max ln L)
    post = prior * np.exp(loglik - loglik.max(axis=1, keepdims=True))
    total = post.sum(axis=1, keepdims=True)
    return np.where(total > 0, post / np.where(total > 0, total, 1.0), 1.0 / belief.shape[1])


@functools.lru_cache(maxsize=64)
def _flat_transition(levels: tuple[int, ...], eps: float, params: FloorParams) -> np.ndarray:
    """Return ``transition_matrix`` without a climb, read-only: one per site and ε."""
    T = transition_matrix(np.array(levels), eps, 0.0, params.climb_switch_prob, params.climb_min_m)
    T.flags.writeable = False
    return T


class FloorFilter:
    """Forward filter over one device's floor.

    A floor is active while its transmitters were heard within
    ``history_ms``: the filter keeps the last time each floor was heard.

    Parameters
    ----------
    levels : ndarray of int, shape (F,)
        Storey of each floor of the site.
    params : FloorParams
    state : dict, optional
        A :meth:`snapshot` to resume from; one that still holds the ring of
        heard counts it replaced resumes too.
    """

    uses_evidence: ClassVar[bool] = True
    """The belief is updated with the window's ``loglik``."""

    def __init__(
        self, levels: np.ndarray, params: FloorParams, state: dict[str, Any] | None = None
    ) -> None:
        self.levels = np.asarray(levels, dtype=np.int64)
        self.params = params
        n = self.levels.size
        state = state or {}
        self.belief = np.asarray(state.get("belief", np.full(n, 1.0 / max(n, 1))), float).copy()
        self.last_t = int(state.get("last_t", NEVER))
        self.heard_t = _heard_times(state, n)
        self.pressure = PressureHistory(state)
        self.current = int(state.get("current", -1))

    def snapshot(self) -> dict[str, Any]:
        """Return the belief, when each floor was last heard and the pressure history."""
        return {
            "belief": self.belief.copy(),
            "last_t": self.last_t,
            "heard_t": self.heard_t.copy(),
            **self.pressure.snapshot(),
            "current": self.current,
        }

    def update(self, window: FloorWindow) -> np.ndarray:
        """Add one window and return the active floors, the chosen floor first.

        The window's ``loglik`` is its evidence (none: the transition alone).

        Returns
        -------
        ndarray of int
            The chosen floor, then the other active floors by decreasing
            belief; empty when no floor was heard within ``history_ms``.
        """
        return self.update_many([self], [window])[0]

    @classmethod
    def update_many(
        cls, filters: Sequence[FloorFilter], windows: Sequence[FloorWindow]
    ) -> list[np.ndarray]:
        """:meth:`update` for many devices of one site, one numpy pass per step.

        A device's result does not depend on which others share the call:
        every row is computed on its own, in the same order of operations.
        """
        if not filters:
            return []
        p = filters[0].params
        d, n = len(filters), filters[0].levels.size
        t = np.array([w.t for w in windows], dtype=np.int64)
        loglik = np.stack([np.zeros(n) if w.loglik is None else w.loglik for w in windows])
        belief = np.stack([f.belief for f in filters])
        heard_t = np.stack([f.heard_t for f in filters])
        last_t = np.array([f.last_t for f in filters], dtype=np.int64)
        # windows since the previous update: a gap lets the belief relax towards uniform
        gap = np.where(last_t == NEVER, 1, np.maximum((t - last_t) // p.window_ms, 1))
        levels = tuple(filters[0].levels.tolist())
        # P = Tⁿ per device: the flat transition of its ε, or its own where it climbs
        power = np.empty((d, n, n))
        for i, (f, w) in enumerate(zip(filters, windows, strict=True)):
            barometer, climb = f.pressure.update(int(t[i]), w.pressure_hpa, p)
            # with a barometer, floors change only in the direction of a climb
            eps = p.flat_switch_prob if barometer else p.switch_prob
            if abs(climb) >= p.climb_min_m:
                T = transition_matrix(f.levels, eps, climb, p.climb_switch_prob, p.climb_min_m)
            else:
                T = _flat_transition(levels, eps, p)
            power[i] = T if gap[i] == 1 else np.linalg.matrix_power(T, int(gap[i]))
        belief = forward_steps(belief, power, loglik)
        # the floors of the window's readings were heard now
        sizes = [len(w.floor) for w in windows]
        device = np.repeat(np.arange(d), sizes)
        floor = np.concatenate([np.asarray(w.floor, np.intp) for w in windows] + [device[:0]])
        # a reading of a transmitter on no floor (-1) makes no floor heard
        placed = floor >= 0
        counts = np.bincount(device[placed] * n + floor[placed], minlength=d * n)
        heard = counts.reshape(d, n) > 0
        heard_t = np.where(heard, t[:, None], heard_t)
        active = heard_t > (t - p.history_ms)[:, None]
        # the chosen floor (the belief's argmax) first, then the active floors by belief
        order = np.argsort(-belief, axis=1, kind="stable")
        ranked_active = np.take_along_axis(active, order, axis=1)
        ranked_active[:, 0] = True
        out = []
        for i, f in enumerate(filters):
            f.belief, f.heard_t, f.last_t = belief[i], heard_t[i], int(t[i])
            if active[i].any():
                f.current = int(order[i, 0])
                out.append(order[i][ranked_active[i]])
            else:
                f.current = -1
                out.append(order[i, :0])
        return out


def _heard_times(state: dict[str, Any], n: int) -> np.ndarray:
    """Return when each floor was last heard (ms): from a snapshot, or never.

    A snapshot from before keeps a ring of windows' times ``t`` and heard
    counts ``heard`` (windows, F) instead: each floor's newest window with a
    reading is the same thing.
    """
    if "heard_t" in state:
        return np.asarray(state["heard_t"], dtype=np.int64).copy()
    if "heard" in state:
        t = np.asarray(state["t"], dtype=np.int64)
        heard = np.asarray(state["heard"], dtype=float) > 0
        return np.where(heard, t[:, None], NEVER).max(axis=0, initial=NEVER)
    return np.full(n, NEVER, dtype=np.int64)
