"""One positioning window as floor selection sees it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NEVER = np.iinfo(np.int64).min // 2
"""Time (ms) standing for "never"; halved so that differences cannot overflow."""


@dataclass(frozen=True, eq=False)
class FloorWindow:
    """One window's readings and barometer, as every floor selector takes them.

    Attributes
    ----------
    t : int
        Window time (ms), increasing from window to window.
    floor, rssi, A : ndarray, shape (n,)
        Floor of each reading's transmitter, the reading (dBm) and the
        transmitter's A (dBm, NaN for a transmitter without a path-loss model).
    loglik : ndarray, shape (F,), optional
        ln p(readings | floor) up to a constant (``FloorEvidence.log_likelihood``),
        given to selectors that use evidence; none is no evidence.
    pressure_hpa : ndarray, optional
        Barometer readings (hPa) of the window.
    """

    t: int
    floor: np.ndarray
    rssi: np.ndarray
    A: np.ndarray
    loglik: np.ndarray | None = None
    pressure_hpa: np.ndarray | None = None
