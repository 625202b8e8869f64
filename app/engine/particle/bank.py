"""Stacked storage of many floor filters, one row per filter."""

from __future__ import annotations

from typing import Any

import numpy as np

NEVER = np.iinfo(np.int64).min // 2
"""Time (ms) standing for "never"; halved so that differences cannot overflow."""


class ParticleBank:
    """Stacked storage for many floor filters: row ``slot`` of each array is one filter.

    Attributes
    ----------
    x, y, alpha : ndarray of float32, shape (S, N)
        Positions (m) and directions (rad clockwise from +y).
    w : ndarray of float64, shape (S, N)
        Weights.
    sampled : ndarray of bool, shape (S,)
        Whether step 1 has run.
    last_radio, last_weights : ndarray of int64, shape (S,)
        Time (ms) of the last window with readings and of the last weight update.
    radius : ndarray of float64, shape (S,)
        68% radius (m) at the last update, the indoor radius of the fix pull.
    """

    _ROWS = ("x", "y", "alpha", "w")
    _SCALARS = ("sampled", "last_radio", "last_weights", "radius")

    def __init__(self, n_particles: int, capacity: int = 8) -> None:
        self.n = n_particles
        self.x = np.zeros((0, n_particles), np.float32)
        self.y = np.zeros((0, n_particles), np.float32)
        self.alpha = np.zeros((0, n_particles), np.float32)
        self.w = np.zeros((0, n_particles), np.float64)
        self.sampled = np.zeros(0, bool)
        self.last_radio = np.zeros(0, np.int64)
        self.last_weights = np.zeros(0, np.int64)
        self.radius = np.zeros(0)
        self._free: list[int] = []
        self._grow(capacity)

    def _grow(self, capacity: int) -> None:
        old = self.x.shape[0]
        if capacity <= old:
            return
        for name in self._ROWS:
            a = getattr(self, name)
            b = np.zeros((capacity, self.n), a.dtype)
            b[:old] = a
            setattr(self, name, b)
        for name in self._SCALARS:
            a = getattr(self, name)
            b = np.zeros(capacity, a.dtype)
            b[:old] = a
            setattr(self, name, b)
        self._free.extend(range(capacity - 1, old - 1, -1))

    def allocate(self) -> int:
        """Return a fresh, never-sampled slot."""
        if not self._free:
            self._grow(max(8, 2 * self.x.shape[0]))
        slot = self._free.pop()
        self.sampled[slot] = False
        self.last_radio[slot] = NEVER
        self.last_weights[slot] = NEVER
        self.radius[slot] = np.inf
        return slot

    def release(self, slot: int) -> None:
        """Return a slot to the pool."""
        self._free.append(slot)

    def export(self, slot: int) -> dict[str, Any]:
        """Return a copy of one filter's state as arrays and scalars."""
        out: dict[str, Any] = {name: getattr(self, name)[slot].copy() for name in self._ROWS}
        out["sampled"] = bool(self.sampled[slot])
        out["last_radio"] = int(self.last_radio[slot])
        out["last_weights"] = int(self.last_weights[slot])
        out["radius"] = float(self.radius[slot])
        return out

    def restore(self, state: dict[str, Any]) -> int:
        """Allocate a slot holding an exported state exactly."""
        slot = self.allocate()
        for name in self._ROWS:
            getattr(self, name)[slot] = np.asarray(state[name])
        self.sampled[slot] = bool(state["sampled"])
        self.last_radio[slot] = int(state["last_radio"])
        self.last_weights[slot] = int(state["last_weights"])
        self.radius[slot] = float(state["radius"])
        return slot
