"""A held-out walk as another phone would record it: WiFi louder, or carried turned."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.engine.pdr_kernel import rotation_heading
from app.evaluation.ilc.server import louder, turned
from tests.evaluation.ilc.test_floor_change import _walk


def test_a_louder_phone_hears_every_access_point_louder_and_nothing_else_changes() -> None:
    walk = _walk("w", "F1", 1_000_000)
    shifted = louder(walk, 6.0)
    np.testing.assert_array_equal(shifted.wifi.rssi, walk.wifi.rssi + 6.0)
    np.testing.assert_array_equal(shifted.wifi.last_seen, walk.wifi.last_seen)
    np.testing.assert_array_equal(shifted.beacons.rssi, walk.beacons.rssi)
    np.testing.assert_array_equal(shifted.waypoints, walk.waypoints)
    # the recording itself is left as it was
    assert walk.wifi.rssi[0] == -60.0
    assert louder(walk, 0.0) is walk


def test_a_turned_phone_reports_every_heading_turned_clockwise_and_nothing_else_changes() -> None:
    walk = _walk("w", "F1", 1_000_000)
    # the phone faces 20°, 100° and 250° east of north, tilted
    rot = []
    for k, heading in enumerate((20.0, 100.0, 250.0)):
        yaw = np.radians(-heading) / 2
        tilt = np.radians(10.0 * k) / 2
        # q = q_z(yaw) q_x(tilt), (x, y, z) of (w, x, y, z)
        w, x, y, z = (
            np.cos(yaw) * np.cos(tilt),
            np.cos(yaw) * np.sin(tilt),
            np.sin(yaw) * np.sin(tilt),
            np.sin(yaw) * np.cos(tilt),
        )
        rot.append([1_000_000 + 100 * k, x, y, z])
    walk = replace(walk, rot=np.array(rot))
    out = turned(walk, 30.0)
    for (_, x, y, z), (_, x2, y2, z2) in zip(walk.rot, out.rot, strict=True):
        w = np.sqrt(max(1.0 - x * x - y * y - z * z, 0.0))
        w2 = np.sqrt(max(1.0 - x2 * x2 - y2 * y2 - z2 * z2, 0.0))
        turn = rotation_heading(x2, y2, z2, w2) - rotation_heading(x, y, z, w)
        assert (turn + 180.0) % 360.0 - 180.0 == pytest.approx(30.0, abs=1e-6)
    np.testing.assert_array_equal(out.rot[:, 0], walk.rot[:, 0])
    np.testing.assert_array_equal(out.acc, walk.acc)
    np.testing.assert_array_equal(out.wifi.rssi, walk.wifi.rssi)
    assert turned(walk, 0.0) is walk
