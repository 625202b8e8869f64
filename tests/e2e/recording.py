"""A synthetic walk on the test floor: WiFi scans from the path-loss model, seeded."""

from __future__ import annotations

import numpy as np

from tests.conftest import FLOOR_DOC

T0 = 1_700_000_000_000


def transmitters() -> list[tuple[str, np.ndarray, float, float, float]]:
    """Return (id, xy, A, B, sigma) of the test floor's transmitters."""
    out = []
    for f in FLOOR_DOC["features"]:
        p = f["properties"]
        if p["kind"] == "transmitter":
            out.append(
                (
                    p["id"],
                    np.array(f["geometry"]["coordinates"][:2], float),
                    p["A"],
                    p["B"],
                    p["sigma"],
                )
            )
    return out


def walk(seconds: int, *, seed: int = 7) -> list[dict]:
    """Return WiFi samples of a walk from (2, 8) to (18, 8) at 0.5 m/s, one scan a second."""
    rng = np.random.default_rng(seed)
    samples = []
    for s in range(seconds):
        pos = np.array([2.0 + 0.5 * s, 8.0])
        for k, (tx_id, xy, A, B, sigma) in enumerate(transmitters()):
            r = max(0.5, float(np.linalg.norm(pos - xy)))
            # rssi = A - B ln r + noise
            rssi = A - B * np.log(r) + sigma * rng.standard_normal()
            samples.append(
                {"t": T0 + 1000 * s + 20 * k, "id": tx_id, "rssi": round(float(rssi), 1)}
            )
    return samples


def batches(samples: list[dict], size: int, *, site: str, device: str) -> list[dict]:
    """Split samples into ingest bodies of ``size`` samples each."""
    return [
        {"device_id": device, "site_id": site, "wifi": samples[i : i + size]}
        for i in range(0, len(samples), size)
    ]
