"""A held-out walk as another make of phone would record it: WiFi louder, nothing else."""

from __future__ import annotations

import numpy as np

from app.evaluation.ilc.server import louder
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
