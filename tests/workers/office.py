"""A person walking through the demo office, as the samples a UWB tag and a BLE phone report."""

from __future__ import annotations

from typing import Any

import numpy as np

from app.demo import load_map

T0 = 1_700_000_000_000
"""Measurement time (ms) the walk starts at."""

ROUTE = np.array([(5.0, 10.0), (23.0, 10.0), (23.0, 4.0), (20.0, 3.0)])
"""Along the corridor, then through the door into the Lab (entered after about 20 s)."""

Sample = dict[str, Any]


def _emitters(kind: str) -> dict[str, np.ndarray]:
    features = load_map()["features"]
    return {
        f["properties"]["id"]: np.array(f["geometry"]["coordinates"], float)
        for f in features
        if f["properties"]["kind"] == kind
    }


def position(seconds: float, route: np.ndarray = ROUTE) -> np.ndarray:
    """Return (x, y, 1 m) after walking ``seconds`` at 1 m/s along ``route`` (then standing)."""
    legs = np.linalg.norm(np.diff(route, axis=0), axis=1)
    s = min(seconds, float(legs.sum()))
    along = np.concatenate([[0.0], np.cumsum(legs)])
    return np.array([np.interp(s, along, route[:, 0]), np.interp(s, along, route[:, 1]), 1.0])


def uwb_ranges(seconds: int, route: np.ndarray = ROUTE) -> list[Sample]:
    """Return exact ranges to the office's five anchors, ten epochs a second."""
    anchors = _emitters("anchor")
    return [
        {"t": T0 + 100 * k, "anchor": name, "range": round(float(np.linalg.norm(p - xyz)), 3)}
        for k in range(seconds * 10)
        for p in [position(k / 10, route)]
        for name, xyz in anchors.items()
    ]


def ble_scans(seconds: int, route: np.ndarray = ROUTE, seed: int = 1) -> list[Sample]:
    """Return one noisy scan of the office's ten beacons a second (path loss as on the map)."""
    rng = np.random.default_rng(seed)
    beacons = _emitters("transmitter")
    out = []
    for k in range(seconds):
        p = position(k, route)
        for i, (name, xyz) in enumerate(beacons.items()):
            d = max(float(np.linalg.norm(p - xyz)), 0.5)
            rssi = -59.0 - 10 * 0.9 * np.log10(d) + rng.normal(0, 2)
            out.append({"t": T0 + 1000 * k + 10 * i, "id": name, "rssi": round(float(rssi), 1)})
    return out


def per_second(samples: list[Sample]) -> list[list[Sample]]:
    """Split time-ordered samples into one upload per second of measurement time."""
    chunks: dict[int, list[Sample]] = {}
    for s in samples:
        chunks.setdefault((s["t"] - T0) // 1000, []).append(s)
    return [chunks[k] for k in sorted(chunks)]


class Clock:
    """A wall clock (epoch ms) that moves only when the test moves it."""

    def __init__(self, now: int = T0) -> None:
        self.now = now

    def __call__(self) -> int:
        return self.now

    def advance(self, seconds: float) -> None:
        """Let ``seconds`` of wall time pass."""
        self.now += round(seconds * 1000)
