"""ILC reader: parsing against a naive second parser, floor levels, stale WiFi, floor maps."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
import shapely

from app.datasets import data_dir
from app.datasets.ilc import (
    BeaconScan,
    Walk,
    WifiScan,
    floor_level,
    floor_map_geojson,
    fresh_wifi,
    imu_samples,
    read_floor,
    read_walk,
    read_waypoints,
    site_walks,
)
from app.geometry.floormap import parse_floor_map

SITE = data_dir() / "ilc" / "site1"
FLOORS = ("B1", "F1", "F2", "F3", "F4")
WALK = SITE / "F1" / "path_data_files" / "5dd9e7aac5b77e0006b1732b.txt.gz"

pytestmark = pytest.mark.skipif(not SITE.is_dir(), reason="ILC site1 recordings not present")


def _naive_parse(path: Path) -> dict[str, list[list[str]]]:
    """Split every data line into fields: the reference the vectorised reader must match."""
    rows: dict[str, list[list[str]]] = {}
    with gzip.open(path, "rt", encoding="utf-8") as fh:
        for line in fh:
            fields = line.rstrip("\n").split("\t")
            if fields[0].startswith("#") or len(fields) < 2:
                continue
            rows.setdefault(fields[1], []).append(fields)
    return rows


def _sorted_rows(rows: list[list[str]]) -> list[list[str]]:
    return sorted(rows, key=lambda r: int(r[0]))


def test_read_walk_matches_a_naive_line_parser_on_every_array() -> None:
    walk = read_walk(WALK)
    ref = _naive_parse(WALK)
    assert walk.walk_id == "5dd9e7aac5b77e0006b1732b"
    assert walk.floor == "F1"
    for name, typ in (
        ("acc", "TYPE_ACCELEROMETER"),
        ("gyro", "TYPE_GYROSCOPE"),
        ("mag", "TYPE_MAGNETIC_FIELD"),
        ("rot", "TYPE_ROTATION_VECTOR"),
    ):
        expected = np.array([[float(v) for v in (r[0], *r[2:5])] for r in _sorted_rows(ref[typ])])
        assert getattr(walk, name).shape == (1579, 4)
        np.testing.assert_array_equal(getattr(walk, name), expected)

    wifi = _sorted_rows(ref["TYPE_WIFI"])
    assert len(walk.wifi) == len(wifi) == 2398
    assert walk.wifi.t.dtype == np.int64 and walk.wifi.last_seen.dtype == np.int64
    np.testing.assert_array_equal(walk.wifi.t, [int(r[0]) for r in wifi])
    np.testing.assert_array_equal(walk.wifi.bssid, [r[3] for r in wifi])
    np.testing.assert_array_equal(walk.wifi.rssi, [float(r[4]) for r in wifi])
    np.testing.assert_array_equal(walk.wifi.freq, [int(r[5]) for r in wifi])
    np.testing.assert_array_equal(walk.wifi.last_seen, [int(r[6]) for r in wifi])

    beacons = _sorted_rows(ref["TYPE_BEACON"])
    assert len(walk.beacons) == len(beacons) == 37
    np.testing.assert_array_equal(walk.beacons.id, ["_".join(r[2:5]) for r in beacons])
    np.testing.assert_array_equal(walk.beacons.tx_power, [float(r[5]) for r in beacons])
    np.testing.assert_array_equal(walk.beacons.rssi, [float(r[6]) for r in beacons])
    np.testing.assert_array_equal(walk.beacons.mac, [r[8] for r in beacons])

    # The last waypoint line of this file is written out of time order.
    expected_wp = np.array([[float(v) for v in r[0:1] + r[2:4]] for r in ref["TYPE_WAYPOINT"]])
    assert walk.waypoints.shape == (7, 3)
    np.testing.assert_array_equal(walk.waypoints, expected_wp[np.argsort(expected_wp[:, 0])])
    np.testing.assert_array_equal(read_waypoints(WALK), walk.waypoints)
    np.testing.assert_array_equal(walk.waypoints[0], [1574559495263, 81.317215, 93.31349])


def test_site_walks_lists_every_file_sorted_by_level() -> None:
    walks = site_walks(SITE)
    assert len(walks) == sum(
        len(list((SITE / f / "path_data_files").glob("*.txt.gz"))) for f in FLOORS
    )
    levels = [floor_level(f) for f, _ in walks]
    assert levels == sorted(levels)
    assert walks[0][0] == "B1" and walks[-1][0] == "F4"
    assert all(p.parent.parent.name == f for f, p in walks)


@pytest.mark.parametrize(
    ("name", "level"),
    [("B2", -2), ("B1", -1), ("F1", 0), ("F2", 1), ("F10", 9), ("1F", 0), ("3F", 2), ("G", 0)],
)
def test_floor_level_maps_names_to_levels(name: str, level: int) -> None:
    assert floor_level(name) == level


def test_floor_level_rejects_unknown_names() -> None:
    with pytest.raises(ValueError, match="unknown floor"):
        floor_level("Mezzanine")


def test_fresh_wifi_drops_readings_older_than_the_age_limit() -> None:
    scan = WifiScan(
        t=np.array([1000, 1000, 1000, 5000], dtype=np.int64),
        bssid=np.array(["a", "b", "c", "a"]),
        rssi=np.array([-50.0, -60.0, -70.0, -55.0]),
        freq=np.array([2412, 2412, 5180, 2412], dtype=np.int64),
        last_seen=np.array([1000, -1000, -1001, 2999], dtype=np.int64),
    )
    fresh = fresh_wifi(scan, max_age_ms=2000)
    np.testing.assert_array_equal(fresh.bssid, ["a", "b"])
    np.testing.assert_array_equal(fresh.rssi, [-50.0, -60.0])
    assert len(fresh_wifi(scan, max_age_ms=0)) == 1


def _stream(t: list[int], value: float) -> np.ndarray:
    return np.column_stack([np.array(t, dtype=float), np.full((len(t), 3), value)])


def test_imu_samples_aligns_streams_on_the_union_of_times_with_nan_gaps() -> None:
    empty_wifi = WifiScan(*(np.zeros(0, dtype=np.int64) for _ in range(5)))
    empty_beacons = BeaconScan(*(np.zeros(0) for _ in range(5)))
    rot = np.array([[10.0, 0.0, 0.0, np.sin(np.pi / 4)], [30.0, 0.6, 0.0, 0.0]])
    walk = Walk(
        walk_id="w",
        floor="F1",
        path=Path("w.txt.gz"),
        acc=_stream([10, 20, 30], 1.0),
        gyro=_stream([20], 2.0),
        mag=_stream([10, 30], 3.0),
        rot=rot,
        wifi=empty_wifi,
        beacons=empty_beacons,
        waypoints=np.zeros((0, 3)),
    )
    imu = imu_samples(walk)
    np.testing.assert_array_equal(imu.t, [10, 20, 30])
    np.testing.assert_array_equal(imu.acc[:, 0], [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(np.isnan(imu.gyro[:, 0]), [True, False, True])
    np.testing.assert_array_equal(np.isnan(imu.mag[:, 0]), [False, True, False])
    # w = sqrt(1 - x² - y² - z²): cos(π/4) and 0.8 for the two rotation samples.
    np.testing.assert_allclose(imu.rot[[0, 2], 3], [np.cos(np.pi / 4), 0.8], rtol=1e-12)
    assert np.isnan(imu.rot[1]).all()


@pytest.mark.parametrize("floor", FLOORS)
def test_floor_map_passes_server_validation_and_holds_the_walked_waypoints(floor: str) -> None:
    doc = floor_map_geojson(SITE / floor)
    fmap = parse_floor_map(doc)
    assert doc["properties"]["level"] == floor_level(floor)
    kinds = [f["properties"]["kind"] for f in doc["features"]]
    assert kinds[0] == "outline" and set(kinds[1:]) == {"barrier"}
    waypoints = np.concatenate([read_waypoints(p) for f, p in site_walks(SITE) if f == floor])
    inside = shapely.contains_xy(fmap.walkable, waypoints[:, 1], waypoints[:, 2])
    assert inside.mean() >= 0.98
    assert shapely.contains_xy(fmap.outline, waypoints[:, 1], waypoints[:, 2]).all()


def test_floor_map_scales_the_polygon_bounding_box_to_the_plan_size() -> None:
    src = read_floor(SITE / "F1")
    fmap = parse_floor_map(src.geojson)
    all_bounds = np.array(
        [shapely.geometry.shape(f["geometry"]).bounds for f in src.geojson["features"]]
    )
    np.testing.assert_allclose(all_bounds[:, :2].min(axis=0), [0.0, 0.0], atol=1e-3)
    np.testing.assert_allclose(all_bounds[:, 2:].max(axis=0), [src.width, src.height], atol=1e-3)
    assert fmap.outline.bounds[2] <= src.width + 1e-3
    assert src.image.is_file()
    coords = shapely.get_coordinates(fmap.outline)
    np.testing.assert_array_equal(coords, np.round(coords, 3))


def test_rooms_walkable_names_shops_as_rooms_and_keeps_voids_as_barriers() -> None:
    doc = floor_map_geojson(SITE / "F2", rooms_walkable=True)
    fmap = parse_floor_map(doc)
    rooms = [f for f in doc["features"] if f["properties"]["kind"] == "room"]
    barriers = [f for f in doc["features"] if f["properties"]["kind"] == "barrier"]
    assert rooms and all(f["geometry"]["type"] == "Polygon" for f in rooms)
    assert {f["properties"]["name"] for f in barriers} <= {"zhongkong", "feikaifangquyu"}
    assert "zhongkong" in {f["properties"]["name"] for f in barriers}
    assert fmap.walkable.area > parse_floor_map(floor_map_geojson(SITE / "F2")).walkable.area


def test_shipped_site1_maps_are_the_converters_output(tmp_path: Path) -> None:
    """maps/site1 is exactly what `locus ilc-maps` writes: it cannot drift from the converter."""
    import json

    from app.cli import main

    assert main(["ilc-maps", str(SITE), str(tmp_path)]) == 0
    shipped = Path(__file__).resolve().parents[2] / "maps" / "site1"
    for name in FLOORS:
        fresh = json.loads((tmp_path / f"{name}.geojson").read_text())
        assert json.loads((shipped / f"{name}.geojson").read_text()) == fresh
        parse_floor_map(fresh)  # the server's own validation accepts it
