"""Reader for the Microsoft Indoor Location Competition 2.0 recordings (``ilc/``).

A site folder holds one folder per floor (``B1``, ``F1``, ...), each with
``floor_info.json`` (plan width and height in metres), ``geojson_map.json``
(the plan's polygons in longitude/latitude), ``floor_image.png`` and
``path_data_files/*.txt.gz``: one walk per file, tab-separated lines
``t  TYPE  values...`` with t in milliseconds.

Parsing groups the lines of a file by type once and converts each group to an
array in one call, so reading the whole 580-walk site takes seconds rather
than the minutes a per-value Python loop would.
"""

from __future__ import annotations

import gzip
import io
import json
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.affinity import affine_transform
from shapely.geometry import mapping, shape
from shapely.geometry.base import BaseGeometry

from app.engine.samples import ImuSamples

FLOOR_LEVELS: dict[str, int] = {f"B{n}": -n for n in range(1, 10)} | {
    f"F{n}": n - 1 for n in range(1, 100)
}
"""Floor name → level (0 ground, -1 first basement) for the ``B<n>``/``F<n>`` names ILC uses."""

DEFAULT_FLOOR_HEIGHT_M = 4.0
"""Floor-to-floor height written into converted maps: the API default, as the
recordings carry no barometer or survey of storey heights to measure it from."""

NEVER_WALKABLE = ("zhongkong", "feikaifangquyu", "中空", "非开放区域")
"""Polygon names that stay barriers even when rooms are walkable: atrium voids
(中空, "zhongkong") and closed areas (非开放区域, "feikaifangquyu")."""

MIN_PIECE_AREA_M2 = 0.01
"""Polygon pieces smaller than this after cleaning are slivers and dropped."""

COORD_DECIMALS = 3
"""Converted coordinates are rounded to millimetres."""

_SENSOR_TYPES = {
    "TYPE_ACCELEROMETER": "acc",
    "TYPE_GYROSCOPE": "gyro",
    "TYPE_MAGNETIC_FIELD": "mag",
    "TYPE_ROTATION_VECTOR": "rot",
}
# Fields per line (t and TYPE included) of the types read; others are skipped.
_FIELDS = {
    "TYPE_ACCELEROMETER": 6,
    "TYPE_GYROSCOPE": 6,
    "TYPE_MAGNETIC_FIELD": 6,
    "TYPE_ROTATION_VECTOR": 6,
    "TYPE_WIFI": 7,
    "TYPE_BEACON": 10,
    "TYPE_WAYPOINT": 4,
}


@dataclass(frozen=True)
class WifiScan:
    """WiFi readings, one row per access point heard, aligned arrays sorted by scan time.

    ``t`` is the scan time (ms) of the line, ``last_seen`` (ms) when the access
    point was actually last heard: it can be seconds older than ``t`` for
    readings the phone repeats from its cache.
    """

    t: np.ndarray
    bssid: np.ndarray
    rssi: np.ndarray
    freq: np.ndarray
    last_seen: np.ndarray

    def __len__(self) -> int:
        return int(self.t.size)

    def take(self, index: np.ndarray) -> WifiScan:
        """Return the rows selected by a boolean mask or an index array."""
        return WifiScan(
            self.t[index],
            self.bssid[index],
            self.rssi[index],
            self.freq[index],
            self.last_seen[index],
        )


@dataclass(frozen=True)
class BeaconScan:
    """iBeacon readings: time (ms), ``UUID_major_minor`` id, RSSI and Tx power (dBm), MAC."""

    t: np.ndarray
    id: np.ndarray
    rssi: np.ndarray
    tx_power: np.ndarray
    mac: np.ndarray

    def __len__(self) -> int:
        return int(self.t.size)


@dataclass(frozen=True)
class Walk:
    """One recorded walk; sensor arrays are (n, 4): t_ms, x, y, z, sorted by time.

    Units: ``acc`` m/s², ``gyro`` rad/s, ``mag`` µT, ``rot`` the Android
    rotation vector (x, y, z; w implied). ``waypoints`` is (m, 3): t_ms, x, y
    (m, the floor's local frame), the surveyed ground truth.
    """

    walk_id: str
    floor: str
    path: Path
    acc: np.ndarray
    gyro: np.ndarray
    mag: np.ndarray
    rot: np.ndarray
    wifi: WifiScan
    beacons: BeaconScan
    waypoints: np.ndarray


@dataclass(frozen=True)
class FloorSource:
    """One floor of a site: name, level, plan extent (m), API floor map and plan image."""

    name: str
    level: int
    width: float
    height: float
    geojson: dict[str, Any]
    image: Path


def floor_level(name: str) -> int:
    """Return the level of a floor name: ``B2`` → -2, ``B1`` → -1, ``F1`` → 0, ``F2`` → 1.

    Also accepts ``1F``/``L1`` (level 0), ``1B`` (-1) and ``G``/``GF`` (0).

    Raises
    ------
    ValueError
        When the name follows none of these conventions.
    """
    key = name.strip().upper()
    if key in FLOOR_LEVELS:
        return FLOOR_LEVELS[key]
    if key in ("G", "GF"):
        return 0
    if m := re.fullmatch(r"(?:[FL](\d+)|(\d+)F)", key):
        return int(m.group(1) or m.group(2)) - 1
    if m := re.fullmatch(r"(?:B(\d+)|(\d+)B)", key):
        return -int(m.group(1) or m.group(2))
    raise ValueError(f"unknown floor name {name!r}")


def _read_text(path: Path) -> str:
    with gzip.open(path, "rt", encoding="utf-8", errors="replace") as fh:
        return fh.read()


def _group_lines(text: str, wanted: Iterable[str]) -> dict[str, list[str]]:
    """Group data lines by TYPE, keeping only the wanted types with their full field count."""
    groups: dict[str, list[str]] = {typ: [] for typ in wanted}
    for line in text.split("\n"):
        if not line or line[0] == "#":
            continue
        parts = line.split("\t", 2)
        if len(parts) == 3 and parts[1] in groups:
            groups[parts[1]].append(line)
    for typ, lines in groups.items():
        n_tabs = _FIELDS[typ] - 1
        groups[typ] = [line for line in lines if line.count("\t") == n_tabs]
    return groups


def _numeric(lines: list[str], columns: tuple[int, ...]) -> np.ndarray:
    """Parse the given tab-separated columns of the lines as float64, shape (n, len(columns))."""
    if not lines:
        return np.zeros((0, len(columns)))
    return np.loadtxt(
        io.StringIO("\n".join(lines)), delimiter="\t", usecols=columns, comments=None, ndmin=2
    )


def _column(lines: list[str], index: int) -> np.ndarray:
    """Return one tab-separated text column of the lines as an array of str."""
    return np.array([line.split("\t")[index] for line in lines], dtype=str)


def _by_time(t: np.ndarray) -> np.ndarray:
    return np.argsort(t, kind="stable")


def _sensor(lines: list[str]) -> np.ndarray:
    xyz = _numeric(lines, (0, 2, 3, 4))
    return xyz[_by_time(xyz[:, 0])]


def read_walk(path: Path, floor: str | None = None) -> Walk:
    """Parse one walk file (``.txt.gz``); the floor defaults to the name of its floor folder.

    Lines of unknown types, headers (``#``) and lines with the wrong number of
    fields are skipped. Every array is sorted by time (stable, so readings of
    one WiFi scan keep their order).
    """
    path = Path(path)
    if floor is None:
        floor = path.parent.parent.name if path.parent.name == "path_data_files" else ""
    groups = _group_lines(_read_text(path), _FIELDS)
    sensors = {name: _sensor(groups[typ]) for typ, name in _SENSOR_TYPES.items()}

    wifi_lines = groups["TYPE_WIFI"]
    # t TYPE ssid bssid rssi freq last_seen
    wnum = _numeric(wifi_lines, (0, 4, 5, 6))
    order = _by_time(wnum[:, 0])
    wifi = WifiScan(
        t=wnum[order, 0].astype(np.int64),
        bssid=_column(wifi_lines, 3)[order] if wifi_lines else np.zeros(0, dtype=str),
        rssi=wnum[order, 1],
        freq=wnum[order, 2].astype(np.int64),
        last_seen=wnum[order, 3].astype(np.int64),
    )

    beacon_lines = groups["TYPE_BEACON"]
    # t TYPE uuid major minor tx_power rssi distance mac t
    bnum = _numeric(beacon_lines, (0, 5, 6))
    order = _by_time(bnum[:, 0])
    ids = np.array(["_".join(line.split("\t")[2:5]) for line in beacon_lines], dtype=str).reshape(
        -1
    )
    beacons = BeaconScan(
        t=bnum[order, 0].astype(np.int64),
        id=ids[order],
        rssi=bnum[order, 2],
        tx_power=bnum[order, 1],
        mac=_column(beacon_lines, 8)[order] if beacon_lines else np.zeros(0, dtype=str),
    )

    waypoints = _numeric(groups["TYPE_WAYPOINT"], (0, 2, 3))
    return Walk(
        walk_id=path.name.split(".")[0],
        floor=floor,
        path=path,
        wifi=wifi,
        beacons=beacons,
        waypoints=waypoints[_by_time(waypoints[:, 0])],
        **sensors,
    )


def read_waypoints(path: Path) -> np.ndarray:
    """Return only the waypoints of a walk file, (m, 3): t_ms, x, y (m), sorted by time.

    Scans for the waypoint lines without parsing anything else: a tenth of
    the cost of ``read_walk`` for tests and maps that need only the truth.
    """
    lines = [
        line
        for line in _read_text(Path(path)).split("\n")
        if "\tTYPE_WAYPOINT\t" in line and line.count("\t") == _FIELDS["TYPE_WAYPOINT"] - 1
    ]
    waypoints = _numeric(lines, (0, 2, 3))
    return waypoints[_by_time(waypoints[:, 0])]


def site_walks(site_dir: Path) -> list[tuple[str, Path]]:
    """Return (floor name, path) of every walk of a site, sorted by floor level then file name."""
    site_dir = Path(site_dir)
    walks = [
        (floor_dir.name, path)
        for floor_dir in site_dir.iterdir()
        if floor_dir.is_dir()
        for path in (floor_dir / "path_data_files").glob("*.txt.gz")
    ]
    return sorted(walks, key=lambda fw: (floor_level(fw[0]), fw[0], fw[1].name))


def site_floors(site_dir: Path) -> list[Path]:
    """Return the floor folders of a site (those with a ``geojson_map.json``), by level."""
    found = [d for d in Path(site_dir).iterdir() if (d / "geojson_map.json").is_file()]
    return sorted(found, key=lambda d: (floor_level(d.name), d.name))


def fresh_wifi(scan: WifiScan, max_age_ms: int = 2000) -> WifiScan:
    """Drop cached readings: keep rows heard at most ``max_age_ms`` before their scan time."""
    # age = t_scan - t_last_seen
    return scan.take(scan.t - scan.last_seen <= max_age_ms)


def imu_samples(walk: Walk) -> ImuSamples:
    """Return the walk's inertial streams as engine ``ImuSamples`` on the union of their times.

    A field is NaN at the times its sensor did not report (in ILC files the
    four sensors share their timestamps, so normally nothing is NaN).
    """
    streams = {"acc": walk.acc, "gyro": walk.gyro, "mag": walk.mag, "rot": walk.rot}
    t = np.unique(np.concatenate([s[:, 0] for s in streams.values()])).astype(np.int64)
    fields: dict[str, np.ndarray] = {}
    for name, stream in streams.items():
        out = np.full((t.size, 3), np.nan)
        st = stream[:, 0].astype(np.int64)
        # Keep the last reading of a repeated timestamp.
        last = np.r_[st[1:] != st[:-1], True] if st.size else np.zeros(0, dtype=bool)
        out[np.searchsorted(t, st[last])] = stream[last, 1:]
        fields[name] = out
    # The Android rotation vector leaves w implied: w = sqrt(max(0, 1 - x² - y² - z²)).
    w = np.sqrt(np.clip(1.0 - np.sum(fields["rot"] ** 2, axis=1, keepdims=True), 0.0, None))
    rot = np.hstack([fields["rot"], w])
    return ImuSamples(t=t, acc=fields["acc"], gyro=fields["gyro"], mag=fields["mag"], rot=rot)


def _polygons(geom: BaseGeometry) -> list[shapely.Polygon]:
    """Return the valid polygon pieces of a geometry, dropping slivers and non-areal parts."""
    if not geom.is_valid:
        geom = shapely.make_valid(geom)
    parts = shapely.get_parts(geom)
    polys: list[shapely.Polygon] = []
    for part in parts:
        if isinstance(part, shapely.Polygon):
            if part.area >= MIN_PIECE_AREA_M2:
                polys.append(part)
        elif isinstance(part, shapely.MultiPolygon | shapely.GeometryCollection):
            polys.extend(_polygons(part))
    return polys


def _clean(geom: BaseGeometry) -> list[shapely.Polygon]:
    """Snap a local-frame geometry to the millimetre grid and return its valid polygon pieces."""
    # set_precision keeps the output valid while snapping every vertex to the grid.
    return _polygons(shapely.set_precision(geom, 10.0**-COORD_DECIMALS))


def _rounded(coords: Any) -> Any:
    if isinstance(coords, list | tuple) and coords and isinstance(coords[0], int | float):
        return [round(float(c), COORD_DECIMALS) for c in coords]
    return [_rounded(c) for c in coords]


def _geometry_json(polys: list[shapely.Polygon]) -> dict[str, Any]:
    geom = polys[0] if len(polys) == 1 else shapely.MultiPolygon(polys)
    doc = mapping(geom)
    return {"type": doc["type"], "coordinates": _rounded(doc["coordinates"])}


def _floor_info(floor_dir: Path) -> tuple[float, float]:
    info = json.loads((floor_dir / "floor_info.json").read_text())["map_info"]
    return float(info["width"]), float(info["height"])


def floor_map_geojson(floor_dir: Path, *, rooms_walkable: bool = False) -> dict[str, Any]:
    """Convert a floor's ``geojson_map.json`` to the API's floor map in local metres.

    The local frame maps the bounding box of all polygons onto the plan's
    width × height: ``x = (lon - lon_min) / (lon_max - lon_min) * width`` and
    likewise for y. The first feature becomes the ``outline``; every other
    polygon a ``barrier`` (surveyors walk the corridors, not the shops) or,
    with ``rooms_walkable``, a named ``room`` (one feature per polygon piece),
    except voids and closed areas (``NEVER_WALKABLE``), which stay barriers.
    Geometry is snapped to millimetres, repaired and stripped of slivers so
    that the server's strict validation accepts it.
    """
    floor_dir = Path(floor_dir)
    width, height = _floor_info(floor_dir)
    source = json.loads((floor_dir / "geojson_map.json").read_text(encoding="utf-8"))
    features = source["features"]
    geoms = [shape(f["geometry"]) for f in features]
    bounds = np.array([g.bounds for g in geoms])
    lon0, lat0 = bounds[:, 0].min(), bounds[:, 1].min()
    lon1, lat1 = bounds[:, 2].max(), bounds[:, 3].max()
    # x = (lon - lon0) * sx, y = (lat - lat0) * sy
    sx, sy = width / (lon1 - lon0), height / (lat1 - lat0)
    to_local = [sx, 0.0, 0.0, sy, -lon0 * sx, -lat0 * sy]

    out: list[dict[str, Any]] = []
    for index, (feature, geom) in enumerate(zip(features, geoms, strict=True)):
        polys = _clean(affine_transform(geom, to_local))
        if not polys:
            continue
        props = feature.get("properties") or {}
        name = str(props.get("name") or props.get("display") or f"polygon {index}").strip()
        if index == 0:
            out.append(
                {
                    "type": "Feature",
                    "properties": {"kind": "outline", "name": name},
                    "geometry": _geometry_json(polys),
                }
            )
        elif rooms_walkable and not any(word in name.lower() for word in NEVER_WALKABLE):
            out.extend(
                {
                    "type": "Feature",
                    "properties": {"kind": "room", "name": name},
                    "geometry": _geometry_json([poly]),
                }
                for poly in polys
            )
        else:
            out.append(
                {
                    "type": "Feature",
                    "properties": {"kind": "barrier", "name": name},
                    "geometry": _geometry_json(polys),
                }
            )
    return {
        "type": "FeatureCollection",
        "properties": {
            "level": floor_level(floor_dir.name),
            "height": DEFAULT_FLOOR_HEIGHT_M,
            "name": floor_dir.name,
            "georef": {"lon": float(lon0), "lat": float(lat0), "rotation_deg": 0.0},
        },
        "features": out,
    }


def read_floor(floor_dir: Path, *, rooms_walkable: bool = False) -> FloorSource:
    """Return a floor's name, level, plan extent (m), API floor map and plan image path."""
    floor_dir = Path(floor_dir)
    width, height = _floor_info(floor_dir)
    return FloorSource(
        name=floor_dir.name,
        level=floor_level(floor_dir.name),
        width=width,
        height=height,
        geojson=floor_map_geojson(floor_dir, rooms_walkable=rooms_walkable),
        image=floor_dir / "floor_image.png",
    )
