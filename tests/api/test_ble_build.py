"""A BLE site calibrates its beacons from its surveys: the flat's six anchors, mapped by
position only, get their path loss from the robot's calibration runs uploaded as surveys,
and the robot's test track is then tracked by the particle filter on it, closer than the
weighted centroid the uncalibrated site had."""

from __future__ import annotations

import uuid
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.datasets import ble_flat
from app.engine.pathloss import ranges_3d

pytestmark = pytest.mark.skipif(
    not (ble_flat.root() / "anchors.csv").exists(), reason="needs the BLE flat recordings"
)

FLOOR = "flat"
RX_HEIGHT_M = 1.2


def _mac(anchor: int) -> str:
    return f"F1:A7:00:00:00:{anchor:02X}"


def _floor(anchors: ble_flat.Anchors) -> dict[str, Any]:
    outline = ble_flat.read_layout().tolist()
    features: list[dict[str, Any]] = [
        {
            "type": "Feature",
            "properties": {"kind": "outline"},
            "geometry": {"type": "Polygon", "coordinates": [outline]},
        }
    ]
    for anchor, (x, y, z) in zip(anchors.ids, anchors.xyz.tolist(), strict=True):
        features.append(
            {
                "type": "Feature",
                "properties": {"kind": "transmitter", "id": _mac(anchor), "tech": "ble", "z": z},
                "geometry": {"type": "Point", "coordinates": [x, y]},
            }
        )
    return {"type": "FeatureCollection", "properties": {"level": 0}, "features": features}


def _ble(track: ble_flat.Track, anchors: ble_flat.Anchors) -> list[dict[str, Any]]:
    row, col = np.nonzero(np.isfinite(track.rssi))
    return [
        {
            "t": int(track.t[r]),
            "id": _mac(anchors.ids[c]),
            "rssi": round(float(track.rssi[r, c]), 2),
        }
        for r, c in zip(row.tolist(), col.tolist(), strict=True)
    ]


def _survey(run: ble_flat.Track, anchors: ble_flat.Anchors) -> dict[str, Any]:
    waypoints = [
        {"t": int(t), "x": x, "y": y}
        for t, (x, y) in zip(run.t.tolist(), run.xy.tolist(), strict=True)
    ]
    return {
        "device_id": "robot",
        "floor_id": FLOOR,
        "waypoints": waypoints,
        "ble": _ble(run, anchors),
    }


def _track_error(
    client: TestClient, admin: dict, site: str, device: str, track: ble_flat.Track
) -> tuple[float, set[str]]:
    """Replay the track's readings as a phone in one-second batches; return the mean error
    of its positions against the robot's and the methods that placed it."""
    samples = _ble(track, ble_flat.read_anchors())
    seconds = [(s["t"] - samples[0]["t"]) // 1000 for s in samples]
    positions: list[dict[str, Any]] = []
    for second in sorted(set(seconds)):
        batch = [s for s, k in zip(samples, seconds, strict=True) if k == second]
        body = {"device_id": device, "site_id": site, "ble": batch}
        r = client.post("/v1/ingest?wait=true", json=body, headers=admin)
        assert r.status_code == 200, r.text
        positions += r.json()["positions"]
    t = np.array([p["t"] for p in positions])
    xy = np.array([[p["x"], p["y"]] for p in positions])
    error = np.linalg.norm(xy - ble_flat.truth_at(track, t), axis=1)
    return float(np.mean(error)), {p["method"] for p in positions}


def test_a_ble_site_calibrates_its_beacons_from_surveys_and_tracks_better_with_them(
    client: TestClient, admin: dict
) -> None:
    anchors = ble_flat.read_anchors()
    site = f"flat-{uuid.uuid4().hex[:6]}"
    assert client.put(f"/v1/sites/{site}", json={"name": site}, headers=admin).status_code == 201
    r = client.put(f"/v1/sites/{site}/floors/{FLOOR}", json=_floor(anchors), headers=admin)
    assert r.status_code == 201, r.text
    test = ble_flat.test_robot()
    test = test.slice(slice(0, int(np.searchsorted(test.t, test.t[0] + 90_000))))
    before, methods = _track_error(client, admin, site, "robot-before", test)
    assert "pf" not in methods, "uncalibrated beacons place no particle filter"

    for run in ble_flat.runs(ble_flat.calibration()):
        r = client.post(f"/v1/sites/{site}/surveys", json=_survey(run, anchors), headers=admin)
        assert r.status_code == 201, r.text
    r = client.post(f"/v1/sites/{site}/radiomap/build", headers=admin)
    assert r.status_code == 200, r.text
    summary = r.json()
    assert summary["scans"] == 0 and summary["ble_windows"] > 1000
    calibration = summary["calibration"]
    assert calibration["calibrated"] == calibration["plausible"] == len(anchors.ids)
    assert calibration["positions_fitted"] == 0, "the map's positions are kept"
    # each beacon's path loss near the plain least squares of RSSI on ln r at the true
    # ranges (the build's fit also weighs what was not heard, and is robust to outliers)
    readings = ble_flat.readings(ble_flat.calibration())
    for fit in calibration["transmitters"]:
        k = [_mac(a).lower() for a in anchors.ids].index(fit["id"])
        mine = readings.tx == k
        xy = ble_flat.truth_at(ble_flat.calibration(), readings.t[mine])
        r_m = ranges_3d(xy, anchors.xyz[k : k + 1], RX_HEIGHT_M, 0.5)[:, 0]
        slope, intercept = np.polyfit(-np.log(r_m), readings.rssi[mine], 1)
        assert abs(fit["A"] - intercept) < 5 and abs(fit["B"] - slope) < 3, (fit, intercept, slope)

    after, methods = _track_error(client, admin, site, "robot-after", test)
    assert methods == {"pf"}, methods
    assert after < before, (after, before)
