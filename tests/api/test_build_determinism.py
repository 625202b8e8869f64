"""A build is a function of its surveys: the same real site1 walks uploaded to two sites
in opposite orders, under other device labels, build byte-identical radio maps, the same
calibration and the same chosen constants, and a replayed walk gets the same positions."""

from __future__ import annotations

import uuid
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.datasets import data_dir
from app.datasets.ilc import read_floor, read_walk, site_walks
from app.importers.ilc import survey_body, walk_samples
from app.radiomaps.models import CalibratedTransmitter, RadioMapBuild, RadioMapFloor
from tests.conftest import ADMIN_KEY

SITE1 = data_dir() / "ilc" / "site1"
FLOOR = "F1"
N_SURVEYS = 5
ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
pytestmark = pytest.mark.skipif(not SITE1.is_dir(), reason="ILC site1 recordings not present")


def _site_with_surveys(client: TestClient, bodies: list[dict[str, Any]], parallel: bool) -> str:
    """Create a site with site1's F1 and upload ``bodies`` as its surveys; its id."""
    sid = f"det-{uuid.uuid4().hex[:8]}"
    assert client.put(f"/v1/sites/{sid}", json={"name": sid}, headers=ADMIN).status_code == 201
    floor = read_floor(SITE1 / FLOOR)
    assert client.put(f"/v1/sites/{sid}/floors/{FLOOR}", json=floor.geojson, headers=ADMIN)

    def upload(body: dict[str, Any]) -> int:
        return client.post(f"/v1/sites/{sid}/surveys", json=body, headers=ADMIN).status_code

    if parallel:
        with ThreadPoolExecutor(max_workers=3) as pool:
            codes = list(pool.map(upload, bodies))
    else:
        codes = [upload(b) for b in bodies]
    assert codes == [201] * len(bodies)
    return sid


def _build(client: TestClient, sid: str) -> dict[str, Any]:
    """Build the site's radio map; every stored row of it, without the site's own id."""
    r = client.post(f"/v1/sites/{sid}/radiomap/build", headers=ADMIN)
    assert r.status_code == 200, r.text
    with client.app.state.locus.sessions() as db:
        maps = db.scalars(
            select(RadioMapFloor)
            .where(RadioMapFloor.site_id == sid)
            .order_by(RadioMapFloor.floor_id)
        ).all()
        fits = db.scalars(
            select(CalibratedTransmitter)
            .where(CalibratedTransmitter.site_id == sid)
            .order_by(CalibratedTransmitter.transmitter_id)
        ).all()
        build = db.get(RadioMapBuild, sid)
        assert build is not None
        columns = [c.name for c in CalibratedTransmitter.__table__.columns if c.name != "site_id"]
        summary = {
            k: v
            for k, v in build.summary.items()
            if k not in ("elapsed_ms", "map_version", "site_id")
        }
        return {
            "maps": [(m.floor_id, m.n_points, m.transmitters, m.data) for m in maps],
            "fits": [{c: getattr(f, c) for c in columns} for f in fits],
            "summary": summary,
        }


def _replay(client: TestClient, sid: str, path: Path) -> list[tuple[Any, ...]]:
    """Post a walk's fresh WiFi to the site as one device; its positions."""
    wifi = [
        s for s in walk_samples(read_walk(path, FLOOR))["wifi"] if s["t"] - s["last_seen"] <= 2000
    ]
    body = {"device_id": "replayed-phone", "site_id": sid, "wifi": wifi}
    r = client.post("/v1/ingest?wait=true", json=body, headers=ADMIN)
    assert r.status_code == 200, r.text
    return [(p["t"], p["x"], p["y"], p["floor_id"], p["accuracy"]) for p in r.json()["positions"]]


def test_the_same_surveys_in_any_order_build_the_same_engine(client: TestClient) -> None:
    paths = [p for f, p in site_walks(SITE1) if f == FLOOR][: N_SURVEYS + 1]
    surveys, replayed = paths[:N_SURVEYS], paths[N_SURVEYS]
    forward = [
        survey_body(read_walk(p, FLOOR), device_id="surveyor-a") | {"name": f"walk {i}"}
        for i, p in enumerate(surveys)
    ]
    backward = [
        survey_body(read_walk(p, FLOOR), device_id=f"surveyor-b{i}") for i, p in enumerate(surveys)
    ][::-1]
    first = _site_with_surveys(client, forward, parallel=False)
    second = _site_with_surveys(client, backward, parallel=True)
    built_first, built_second = _build(client, first), _build(client, second)
    assert built_first["maps"] and built_first["fits"]
    assert built_first == built_second
    positions = _replay(client, first, replayed)
    assert positions and positions == _replay(client, second, replayed)
