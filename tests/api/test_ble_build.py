"""A BLE site calibrates its beacons from its surveys: the flat's six anchors, mapped by
position only, get their path loss from the robot's calibration runs uploaded as surveys,
and the robot's test track is then tracked by the particle filter on it, closer than by
the weighted centroid the uncalibrated site had."""

from __future__ import annotations

from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.datasets import ble_flat
from app.engine.calibration import CalibrationParams
from app.engine.pathloss import ranges_3d
from app.evaluation.ble_flat_http import beacon_id, measure

pytestmark = pytest.mark.skipif(
    not (ble_flat.root() / "anchors.csv").exists(), reason="needs the BLE flat recordings"
)


class _AsAdmin:
    """The test client, every request with the admin key (the client itself is shared)."""

    def __init__(self, client: TestClient, admin: dict[str, str]) -> None:
        self.client, self.admin = client, admin

    def put(self, url: str, *, json: Any) -> httpx.Response:
        return self.client.put(url, json=json, headers=self.admin)

    def post(self, url: str, *, json: Any = None) -> httpx.Response:
        return self.client.post(url, json=json, headers=self.admin)


def test_a_ble_site_calibrates_its_beacons_from_surveys_and_tracks_better_with_them(
    client: TestClient, admin: dict
) -> None:
    run = measure(_AsAdmin(client, admin), seconds=90)

    assert "pf" not in run.before_methods, "uncalibrated beacons place no particle filter"
    summary = run.summary
    assert summary["scans"] == 0 and summary["ble_windows"] > 1000
    calibration = summary["calibration"]
    anchors = ble_flat.read_anchors()
    assert calibration["calibrated"] == calibration["plausible"] == len(anchors.ids)
    assert calibration["positions_fitted"] == 0, "the map's positions are kept"
    # each beacon's path loss near the plain least squares of RSSI on ln r at the true
    # ranges (the build's fit also weighs what was not heard, and is robust to outliers)
    recording = ble_flat.calibration()
    readings = ble_flat.readings(recording)
    ids = [beacon_id(a).lower() for a in anchors.ids]
    for fit in calibration["transmitters"]:
        k = ids.index(fit["id"])
        mine = readings.tx == k
        xy = ble_flat.truth_at(recording, readings.t[mine])
        rx_height = CalibrationParams().rx_height_m
        r_m = ranges_3d(xy, anchors.xyz[k : k + 1], rx_height, 0.5)[:, 0]
        slope, intercept = np.polyfit(-np.log(r_m), readings.rssi[mine], 1)
        assert abs(fit["A"] - intercept) < 5 and abs(fit["B"] - slope) < 3, (fit, intercept, slope)

    assert run.after_methods == {"pf"}
    assert np.mean(run.after) < np.mean(run.before), (np.mean(run.after), np.mean(run.before))
