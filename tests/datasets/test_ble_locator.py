"""BLE locator reader: receivers, tracks in time order, occupancy polarity."""

from __future__ import annotations

import numpy as np
import pytest

from app.datasets.ble_locator import (
    folder,
    locator_site,
    read_locators,
    read_occupancy,
    read_track,
    track_names,
)

pytestmark = pytest.mark.skipif(not folder().exists(), reason="ble_locator recordings not present")


def test_locators_are_the_dongles_line() -> None:
    loc = read_locators()
    assert len(loc.ids) == 12 and loc.xyz.shape == (12, 3)
    i = loc.ids.index("b827eb4521b4")
    assert loc.alias[i] == "sensor10"
    np.testing.assert_array_equal(loc.xyz[i], [7.00, 7.09, 1.22])
    j = loc.ids.index("000000000402")
    np.testing.assert_array_equal(loc.xyz[j], [12.76, 0.27, 2.30])


def test_tracks_are_sorted_and_keep_every_line() -> None:
    names = track_names()
    assert names == [
        "rectangular_with_rotation",
        "straight_01",
        "straight_02",
        "straight_03",
        "zigzagging_with_rotation",
    ]
    loc = read_locators()
    track = read_track("straight_02", loc)
    lines = [
        line.split(",")
        for line in (folder() / "trk" / "straight_02_all_sensors.mbd").read_text().splitlines()
        if line.strip()
    ]
    assert len(track) == len(lines)
    assert np.all(np.diff(track.t) >= 0)
    earliest = min(lines, key=lambda r: float(r[0]))
    assert track.t[0] == round(float(earliest[0]) * 1000)
    assert loc.ids[track.locator[0]] == earliest[1] and track.rssi[0] == float(earliest[3])
    np.testing.assert_array_equal(track.truth[0], [float(v) for v in earliest[4:7]])


def test_zero_cells_are_free_space() -> None:
    plan = read_occupancy(0.2)
    assert plan.cell == pytest.approx(0.2) and plan.shape == (90, 105)
    truth = np.vstack([read_track(n).truth[:, :2] for n in track_names()])
    assert plan.is_free(truth).mean() > 0.95
    assert 0.3 < plan.free.mean() < 0.7


def test_site_carries_path_loss_and_plan() -> None:
    loc = read_locators()
    plan = read_occupancy(0.5)
    site = locator_site(
        loc, A=np.full(12, -60.0), B=np.full(12, 7.0), sigma=np.full(12, 5.0), plan=plan
    )
    assert site.floors[0].plan is plan
    np.testing.assert_array_equal(site.locators.xyz, loc.xyz)
    assert (site.locators.B == 7.0).all()
    bare = locator_site(loc)
    assert np.isnan(bare.locators.A).all() and bare.floors[0].plan.free.all()
