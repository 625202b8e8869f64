"""Survey guidance through the API: real site1 walks uploaded as surveys and built, then
each floor's expected-error grid read as JSON and as a PNG over the plan; 404 saying why
before a build, for a floor the build did not have, and for an unknown floor."""

from __future__ import annotations

import struct
import uuid
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from app.datasets.ilc import read_floor, read_walk, site_walks
from app.importers.ilc import survey_body
from app.radiomaps.models import SurveyGuidanceFloor
from tests.api.test_radiomap import FLOOR, N_SURVEYS, SITE1, needs_site1
from tests.conftest import ADMIN_KEY, make_key

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}


@pytest.fixture(scope="module")
def guided(client: TestClient) -> dict[str, Any]:
    """A site with site1's F1 and 4 of its walks as surveys, read before and after its build;
    the survey bodies, the answer before the build and the build's summary."""
    sid = f"sg-{uuid.uuid4().hex[:8]}"
    assert client.put(f"/v1/sites/{sid}", json={"name": sid}, headers=ADMIN).status_code == 201
    floor = read_floor(SITE1 / FLOOR)
    assert client.put(f"/v1/sites/{sid}/floors/{FLOOR}", json=floor.geojson, headers=ADMIN)
    walks = [p for f, p in site_walks(SITE1) if f == FLOOR][:N_SURVEYS]
    bodies = [survey_body(read_walk(p, FLOOR), device_id="surveyor") for p in walks]
    for body in bodies:
        r = client.post(f"/v1/sites/{sid}/surveys", json=body, headers=ADMIN)
        assert r.status_code == 201, r.text
    before = client.get(f"/v1/sites/{sid}/floors/{FLOOR}/survey-guidance", headers=ADMIN)
    r = client.post(f"/v1/sites/{sid}/radiomap/build", headers=ADMIN)
    assert r.status_code == 200, r.text
    return {"site_id": sid, "bodies": bodies, "before": before, "summary": r.json()}


def scan_positions(body: dict[str, Any]) -> np.ndarray:
    """Return where the walker was at each WiFi scan of a survey body, between its waypoints."""
    wp = np.array([[w["t"], w["x"], w["y"]] for w in body["waypoints"]])
    t = np.unique([s["t"] for s in body["wifi"]])
    t = t[(t >= wp[0, 0]) & (t <= wp[-1, 0])]
    return np.column_stack([np.interp(t, wp[:, 0], wp[:, 1]), np.interp(t, wp[:, 0], wp[:, 2])])


@needs_site1
def test_before_a_build_the_guidance_is_404_saying_how_to_get_one(guided: dict) -> None:
    r = guided["before"]
    assert r.status_code == 404
    assert r.json()["error"]["code"] == "not_found"
    assert "no radio map yet" in r.json()["error"]["message"]
    assert "/radiomap/build" in r.json()["error"]["message"]


@needs_site1
def test_the_grid_is_finite_near_the_survey_and_null_off_the_walkable_area(
    client: TestClient, guided: dict
) -> None:
    sid = guided["site_id"]
    r = client.get(f"/v1/sites/{sid}/floors/{FLOOR}/survey-guidance", headers=ADMIN)
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"
    doc = r.json()
    ny, nx = doc["shape"]
    cell = doc["cell"]
    params = doc["params"]
    assert cell == params["cell_m"] == 2.0 and doc["site_id"] == sid and doc["floor_id"] == FLOOR
    error = np.array(doc["expected_error_m"], dtype=float)  # null -> NaN
    distance = np.array(doc["distance_m"], dtype=float)
    walkable = np.array(doc["walkable"], dtype=bool)
    assert error.shape == distance.shape == walkable.shape == (ny, nx)
    # off the walkable area there is nothing, in either grid
    assert (~walkable).any() and walkable.any()
    assert np.isnan(error[~walkable]).all() and np.isnan(distance[~walkable]).all()
    # every walkable cell within 1.5 m of a surveyed scan has an expected error
    x0, y0 = doc["origin"]
    rows, cols = np.nonzero(walkable)
    centres = np.column_stack([x0 + (cols + 0.5) * cell, y0 + (rows + 0.5) * cell])
    scans = np.vstack([scan_positions(b) for b in guided["bodies"]])
    near = np.min(np.linalg.norm(centres[:, None] - scans[None], axis=-1), axis=1) <= 1.5
    assert near.sum() > 50
    assert np.isfinite(error[rows[near], cols[near]]).all()
    # (a scan whose readings were all too old is not held out: not every one counts)
    assert np.median(distance[rows[near], cols[near]]) <= 1.5
    # cells out of reach of every scan are unsurveyed, with their distance beside them
    finite = np.isfinite(error)
    assert np.all(distance[walkable & ~finite] > params["reach_m"] - 1e-2)
    assert np.all(distance[finite] <= params["reach_m"] + 1e-2)
    # a mean of held-out errors: as large as they are, on average
    assert np.all(error[finite] >= 0)
    held_out = guided["summary"]["accuracy"]["mean_error_m"]
    assert 0.5 * held_out < np.mean(error[finite]) < 2.0 * held_out
    # the build's summary gives the same figures as the grid
    [floor] = guided["summary"]["guidance"]["floors"]
    assert floor == doc["summary"] and floor["floor_id"] == FLOOR
    assert floor["walkable_cells"] == int(walkable.sum())
    assert floor["scans"] == guided["summary"]["accuracy"]["scans"]
    unsurveyed = walkable & ~finite
    assert floor["unsurveyed_share"] == pytest.approx(unsurveyed.sum() / walkable.sum(), abs=1e-4)
    high = walkable & (np.nan_to_num(error) > params["high_error_m"])
    assert floor["high_error_share"] == pytest.approx(high.sum() / walkable.sum(), abs=1e-4)
    assert floor["mean_expected_error_m"] == pytest.approx(np.nanmean(error), abs=2e-3)
    with client.app.state.locus.sessions() as db:
        stored = select(func.count()).where(SurveyGuidanceFloor.site_id == sid)
        assert db.scalar(stored) == 1


def png_size(data: bytes) -> tuple[int, int]:
    """Return a PNG's width and height from its IHDR chunk."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    width, height = struct.unpack(">II", data[16:24])
    return width, height


@needs_site1
def test_the_guidance_is_drawn_as_a_png_for_a_viewer_of_the_site(
    client: TestClient, guided: dict
) -> None:
    sid = guided["site_id"]
    viewer = make_key(client, ADMIN, "viewer", sid)
    path = f"/v1/sites/{sid}/floors/{FLOOR}/survey-guidance"
    by_query = client.get(f"{path}?format=png", headers=viewer)
    by_accept = client.get(path, headers=viewer | {"Accept": "image/png"})
    for r in (by_query, by_accept):
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        width, height = png_size(r.content)
        assert width >= 600 and height >= 200 and len(r.content) > 20_000
    # format=json wins over the Accept header
    r = client.get(f"{path}?format=json", headers=viewer | {"Accept": "image/png"})
    assert r.headers["content-type"] == "application/json" and r.json()["shape"]
    r = client.get(f"{path}?format=svg", headers=viewer)
    assert r.status_code == 422 and "format" in r.text
    device = make_key(client, ADMIN, "device", sid)
    assert client.get(path, headers=device).status_code == 403


@needs_site1
def test_a_floor_the_build_did_not_have_and_an_unknown_floor_are_404(
    client: TestClient, guided: dict
) -> None:
    sid = guided["site_id"]
    geojson = read_floor(SITE1 / "F2").geojson
    assert client.put(f"/v1/sites/{sid}/floors/F2", json=geojson, headers=ADMIN).is_success
    r = client.get(f"/v1/sites/{sid}/floors/F2/survey-guidance", headers=ADMIN)
    assert r.status_code == 404 and "no survey guidance for floor 'F2'" in r.text
    r = client.get(f"/v1/sites/{sid}/floors/nowhere/survey-guidance", headers=ADMIN)
    assert r.status_code == 404 and "floor 'nowhere' not found" in r.text
