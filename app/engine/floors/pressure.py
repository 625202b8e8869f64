"""The barometer's climb: both floor selectors read it from a device's recent pressure.

Air pressure falls about 0.12 hPa per metre climbed, so a change of a storey
shows within seconds of taking the stairs or a lift, while radio needs a few
scans. Pressure is compared only across ``climb_window_ms`` because weather
drifts it by about 1 hPa in three hours.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from app.engine.floors.params import FloorParams


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


class PressureHistory:
    """A device's mean barometer reading per window, kept for ``climb_window_ms``.

    Both floor selectors read the climb from it; its snapshot keys (``p_t``,
    ``p_hpa``) sit inside theirs.
    """

    def __init__(self, state: dict[str, Any] | None = None) -> None:
        state = state or {}
        self.t = np.asarray(state.get("p_t", np.zeros(0, np.int64)), dtype=np.int64).copy()
        self.hpa = np.asarray(state.get("p_hpa", np.zeros(0)), dtype=float).copy()

    def update(
        self, t: int, pressure_hpa: np.ndarray | None, params: FloorParams
    ) -> tuple[bool, float]:
        """Add a window's readings, forget the old ones; return ``pressure_climb``'s answer."""
        if pressure_hpa is not None and len(pressure_hpa):
            self.t = np.append(self.t, t)
            self.hpa = np.append(self.hpa, float(np.mean(pressure_hpa)))
        if not self.t.size:
            # no barometer heard: what ``pressure_climb`` says of no readings
            return False, 0.0
        recent = self.t >= t - params.climb_window_ms
        self.t, self.hpa = self.t[recent], self.hpa[recent]
        return pressure_climb(self.t, self.hpa, t, params)

    def snapshot(self) -> dict[str, Any]:
        """Return the kept times and pressures."""
        return {"p_t": self.t.copy(), "p_hpa": self.hpa.copy()}
