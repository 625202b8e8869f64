"""Validated JSON samples turned into what the engine reads, the same for live and surveys.

Shared by the workers (live batches) and the radio-map build (survey walks,
whose steps fit the site's PDR constants and whose scans make the maps).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from app.engine.samples import ImuSamples

_NAN3 = (np.nan, np.nan, np.nan)


def imu_arrays(imu: Sequence[dict[str, Any]]) -> ImuSamples:
    """Return inertial samples as arrays (NaN where a sample lacks a sensor), in given order."""
    return ImuSamples(
        np.array([s["t"] for s in imu], np.int64),
        np.array([s.get("acc") or _NAN3 for s in imu], float).reshape(-1, 3),
        np.array([s.get("gyro") or _NAN3 for s in imu], float).reshape(-1, 3),
        np.array([s.get("mag") or _NAN3 for s in imu], float).reshape(-1, 3),
        np.array([_rot4(s.get("rot")) for s in imu], float).reshape(-1, 4),
    )


def wifi_times(wifi: Sequence[dict[str, Any]]) -> list[int]:
    """Return the time to give each WiFi reading: its scan's, at the scan's freshest reading.

    Readings sharing ``t`` are one scan. Where they carry ``last_seen``, the
    scan completed up to two seconds after its access points were heard, so
    the scan is timed at its newest ``last_seen``: what the readings
    measured, and the time a client sending per-reading last-seen times
    gives the same scan (both ways of sending a scan then place it alike).
    Readings without ``last_seen`` keep their own ``t``.
    """
    freshest: dict[int, int] = {}
    for s in wifi:
        seen = s.get("last_seen")
        if seen is not None:
            freshest[s["t"]] = max(freshest.get(s["t"], seen), seen)
    return [
        freshest.get(s["t"], s["t"]) if s.get("last_seen") is not None else s["t"] for s in wifi
    ]


def reading_age(reading: dict[str, Any]) -> int:
    """Return how long before its scan's ``t`` a WiFi reading was last heard (ms; 0 without
    ``last_seen``, where the reading's own ``t`` is when it was heard)."""
    seen = reading.get("last_seen")
    return 0 if seen is None else int(reading["t"]) - int(seen)


def _rot4(rot: list[float] | None) -> tuple[float, ...]:
    if rot is None:
        return (np.nan,) * 4
    if len(rot) == 4:
        return tuple(rot)
    # w of a unit quaternion from its vector part (Android omits it on old devices)
    w = float(np.sqrt(max(0.0, 1.0 - sum(v * v for v in rot))))
    return (*rot, w)
