"""Accuracy figures shared by every evaluation: truth, angle wrapping and error statistics."""

from __future__ import annotations

import numpy as np


def truth_at(waypoints: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interpolate surveyed waypoints (m, 3: t, x, y) at times ``t``.

    Returns the positions (n, 2) and a mask of the times inside the waypoints'
    span (the walker moved straight between waypoints; outside it is unknown).
    """
    t = np.asarray(t, dtype=float)
    wt = waypoints[:, 0]
    xy = np.stack([np.interp(t, wt, waypoints[:, 1]), np.interp(t, wt, waypoints[:, 2])], axis=-1)
    return xy, (t >= wt[0]) & (t <= wt[-1])


def error_stats(errors: np.ndarray) -> dict[str, float]:
    """Return count, mean, median, p75 and p95 of horizontal errors (m)."""
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        return {
            "n": 0,
            "mean": float("nan"),
            "median": float("nan"),
            "p75": float("nan"),
            "p95": float("nan"),
        }
    return {
        "n": int(e.size),
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "p75": float(np.percentile(e, 75)),
        "p95": float(np.percentile(e, 95)),
    }


def format_row(name: str, stats: dict[str, float], floor_error: float | None = None) -> str:
    """Return one aligned table row of error statistics."""
    floor = "" if floor_error is None else f" {floor_error * 100:8.2f}%"
    return (
        f"{name:<34} {stats['n']:>7} {stats['mean']:>7.2f} {stats['median']:>7.2f} "
        f"{stats['p75']:>7.2f} {stats['p95']:>7.2f}{floor}"
    )


HEADER = f"{'method':<34} {'n':>7} {'mean':>7} {'median':>7} {'p75':>7} {'p95':>7} {'floor err':>9}"
