"""Import a Microsoft Indoor Location Competition site: floors, then every walk as a survey.

Everything goes through the public HTTP API, so the importer works against
any Locus server and exercises the same validation as any other client.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from rich.progress import Progress

from app.datasets.ilc import Walk, imu_samples, read_floor, read_walk, site_walks


@dataclass(frozen=True)
class ImportSummary:
    """What an import uploaded."""

    floors: int
    surveys: int
    samples: int


def _vector(row: np.ndarray) -> list[float] | None:
    return None if np.isnan(row).any() else [round(float(v), 6) for v in row]


WIFI_TIMES = ("scan", "reading")
"""How WiFi readings are timed: the scan's time as ``t`` with each access point's
``last_seen`` beside it, or each reading's last-seen time as its ``t``."""


def survey_body(walk: Walk, *, device_id: str, wifi_times: str = "scan") -> dict[str, Any]:
    """Return the survey request for one walk.

    Samples go as recorded: the server drops what no radio can produce (some of
    the mall's beacons advertise a transmit power of +69 dBm) and cached WiFi
    readings too old for their scan, and says so.
    """
    return {
        "device_id": device_id,
        "floor_id": walk.floor,
        "name": walk.walk_id,
        "waypoints": [{"t": int(t), "x": float(x), "y": float(y)} for t, x, y in walk.waypoints],
        **walk_samples(walk, wifi_times=wifi_times),
    }


def wifi_samples(walk: Walk, wifi_times: str = "scan") -> list[dict[str, Any]]:
    """Return every WiFi reading of the walk as a phone reports it (see ``WIFI_TIMES``)."""
    w = walk.wifi
    if wifi_times == "reading":
        return [
            {"t": int(w.last_seen[i]), "id": str(w.bssid[i]), "rssi": float(w.rssi[i])}
            | {"freq": int(w.freq[i])}
            for i in range(len(w))
        ]
    return [
        {"t": int(w.t[i]), "id": str(w.bssid[i]), "rssi": float(w.rssi[i])}
        | {"freq": int(w.freq[i]), "last_seen": int(w.last_seen[i])}
        for i in range(len(w))
    ]


def walk_samples(walk: Walk, *, wifi_times: str = "scan") -> dict[str, list[dict[str, Any]]]:
    """Return a walk's WiFi, BLE and IMU samples as ingest sample lists."""
    imu = imu_samples(walk)
    imu_rows = []
    for i in range(len(imu)):
        sample: dict[str, Any] = {"t": int(imu.t[i])}
        for name, values in (
            ("acc", imu.acc[i]),
            ("gyro", imu.gyro[i]),
            ("mag", imu.mag[i]),
            ("rot", imu.rot[i]),
        ):
            vector = _vector(values)
            if vector is not None:
                sample[name] = vector
        if len(sample) > 1:
            imu_rows.append(sample)
    beacons = walk.beacons
    return {
        "wifi": wifi_samples(walk, wifi_times),
        "ble": [
            {"t": int(beacons.t[i]), "id": str(beacons.id[i]), "rssi": float(beacons.rssi[i])}
            | (
                {"tx_power": float(beacons.tx_power[i])}
                if not math.isnan(beacons.tx_power[i])
                else {}
            )
            for i in range(len(beacons))
        ],
        "imu": imu_rows,
    }


def import_site(
    site_dir: Path,
    *,
    site_id: str,
    server: str,
    key: str,
    rooms_walkable: bool = False,
    limit: int | None = None,
    floors: list[str] | None = None,
) -> ImportSummary:
    """Create the site, upload its floors and upload each walk as a survey.

    ``limit`` caps the walks per floor (for quick trials); ``floors`` picks floors by name.
    """
    headers = {"Authorization": f"Bearer {key}"}
    walks = [(f, p) for f, p in site_walks(site_dir) if floors is None or f in floors]
    floor_names = sorted({f for f, _ in walks} | set(floors or []))
    if limit is not None:
        walks = [w for name in floor_names for w in [x for x in walks if x[0] == name][:limit]]
    samples = 0
    with httpx.Client(base_url=server, headers=headers, timeout=300) as http, Progress() as bar:
        http.put(f"/v1/sites/{site_id}", json={"name": site_id}).raise_for_status()
        task = bar.add_task("floors", total=len(floor_names))
        for name in floor_names:
            floor = read_floor(site_dir / name, rooms_walkable=rooms_walkable)
            http.put(f"/v1/sites/{site_id}/floors/{name}", json=floor.geojson).raise_for_status()
            bar.advance(task)
        task = bar.add_task("walks", total=len(walks))

        def prepare(item: tuple[str, Path]) -> dict[str, Any]:
            floor, path = item
            return survey_body(read_walk(path, floor), device_id=f"ilc-{path.name.split('.')[0]}")

        # reading and converting the next walk overlaps with uploading this one
        with ThreadPoolExecutor(max_workers=2) as pool:
            for body in pool.map(prepare, walks):
                r = http.post(f"/v1/sites/{site_id}/surveys", json=body)
                if r.status_code != 201:
                    raise RuntimeError(f"survey {body['name']} rejected: {r.status_code} {r.text}")
                samples += sum(len(body[k]) for k in ("wifi", "ble", "imu"))
                bar.advance(task)
    return ImportSummary(floors=len(floor_names), surveys=len(walks), samples=samples)
