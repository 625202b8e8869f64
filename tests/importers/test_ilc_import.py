"""`locus import-ilc` puts all five site1 floors into a real server; the stored maps'
walkable areas hold at least 98% of each floor's surveyed waypoints."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
import shapely

from app.datasets import data_dir
from app.datasets.ilc import read_waypoints, site_walks
from app.geometry.floormap import parse_floor_map
from tests.conftest import ADMIN_KEY, LiveServer

SITE1 = data_dir() / "ilc" / "site1"


@pytest.mark.skipif(not SITE1.is_dir(), reason="ILC site1 recordings not present")
def test_import_site1_floors_and_walks(live_server: LiveServer, tmp_path: Path) -> None:
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "app.cli",
            "import-ilc",
            str(SITE1),
            "--site-id",
            "site1",
            "--server",
            live_server.url,
            "--key",
            ADMIN_KEY,
            "--limit",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    http = httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {ADMIN_KEY}"})
    floors = http.get("/v1/sites/site1/floors").json()
    assert [(f["floor_id"], f["level"]) for f in floors] == [
        ("B1", -1),
        ("F1", 0),
        ("F2", 1),
        ("F3", 2),
        ("F4", 3),
    ]
    surveys = http.get("/v1/sites/site1/surveys").json()
    assert surveys["total"] == 10
    assert all(s["counts"]["waypoints"] > 0 and s["counts"]["imu"] > 0 for s in surveys["items"])
    for floor in floors:
        walkable = parse_floor_map(
            http.get(f"/v1/sites/site1/floors/{floor['floor_id']}").json()
        ).walkable
        points = np.vstack(
            [read_waypoints(p)[:, 1:] for f, p in site_walks(SITE1) if f == floor["floor_id"]]
        )
        inside = shapely.contains_xy(walkable, points[:, 0], points[:, 1])
        assert inside.mean() >= 0.98, (floor["floor_id"], inside.mean())
