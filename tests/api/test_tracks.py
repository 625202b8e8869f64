"""Tracks: fitted in the pool, stored, and the device's position set; bad tracks get 4xx."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.geometry.floormap import parse_floor_map
from app.geometry.raster import floor_plan
from app.tracks.fitting import run_fit
from tests.conftest import floor_doc

T0 = 1_700_000_000_000


def _track(site: str, **changes: object) -> dict:
    # Along y = 8.5 from x = 2 eastwards: 14 links of 1 m; the dead-reckoned heading
    # drifts 0.05 rad left per link, so the raw track curls north into the outline.
    body = {
        "device_id": f"{site}-saver",
        "site_id": site,
        "floor_id": "G",
        "start": {"x": 2.0, "y": 8.5},
        "t0": T0,
        "heading": 90.0,
        "segments": [
            {"t": T0 + 700 * (i + 1), "length": 1.0, "turn": 0.05 if i else 0.0} for i in range(14)
        ],
    }
    return body | changes


def _wait_done(client: TestClient, admin: dict, track_id: str) -> dict:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        body = client.get(f"/v1/tracks/{track_id}", headers=admin).json()
        if body["status"] in ("done", "failed"):
            return body
        time.sleep(0.1)
    raise AssertionError("fit did not finish")


def test_track_is_fitted_inside_the_plan(client: TestClient, admin: dict, site_id: str) -> None:
    body = _track(site_id)
    r = client.post("/v1/tracks", json=body, headers=admin)
    assert r.status_code == 202, r.text
    result = _wait_done(client, admin, r.json()["track_id"])
    assert result["status"] == "done", result
    points = np.array([[p["x"], p["y"]] for p in result["points"]])
    assert [p["t"] for p in result["points"]] == [T0] + [s["t"] for s in body["segments"]]
    plan = floor_plan(parse_floor_map(floor_doc()), cell=0.25)
    assert plan.segment_free(points[:-1], points[1:]).all()
    # the raw track leaves the building: the fit had to change it
    heading = math.pi / 2 - math.radians(90.0) + np.cumsum([s["turn"] for s in body["segments"]])
    raw = np.vstack(
        [[2.0, 8.5], [2.0, 8.5] + np.cumsum(np.c_[np.cos(heading), np.sin(heading)], axis=0)]
    )
    assert not plan.segment_free(raw[:-1], raw[1:]).all()
    assert result["score"] > 0
    latest = client.get(f"/v1/devices/{site_id}-saver/position", headers=admin).json()
    assert latest["method"] == "trackfit" and latest["t"] == body["segments"][-1]["t"]
    assert (latest["x"], latest["y"]) == (result["points"][-1]["x"], result["points"][-1]["y"])


@pytest.mark.parametrize(
    ("change", "status"),
    [
        ({"segments": []}, 422),
        ({"segments": [{"t": T0 + 1, "length": -1.0, "turn": 0.0}]}, 422),
        ({"segments": [{"t": T0 + 1, "length": 500.0, "turn": 0.0}]}, 422),
        ({"segments": [{"t": T0 - 1, "length": 1.0, "turn": 0.0}]}, 422),
        ({"floor_id": "nope"}, 404),
        ({"site_id": "no-such-site"}, 404),
        ({"start": {"x": 30.0, "y": 5.0}}, 422),
        ({"grid": 0.01}, 422),
    ],
)
def test_bad_tracks_are_rejected(
    client: TestClient, admin: dict, site_id: str, change: dict, status: int
) -> None:
    r = client.post("/v1/tracks", json=_track(site_id, **change), headers=admin)
    assert r.status_code == status, r.text


def test_unfittable_track_fails_with_a_reason(
    client: TestClient, admin: dict, site_id: str
) -> None:
    # 40 m straight east in a 20 m wide building cannot be fitted by 10% scaling
    body = _track(site_id, segments=[{"t": T0 + 1000, "length": 40.0, "turn": 0.0}])
    r = client.post("/v1/tracks", json=body, headers=admin)
    result = _wait_done(client, admin, r.json()["track_id"])
    assert result["status"] == "failed" and "link 1" in result["error"]


def test_unknown_track_is_404(client: TestClient, admin: dict) -> None:
    assert client.get("/v1/tracks/nope", headers=admin).status_code == 404


def test_fit_reports_what_it_chose(client: TestClient, admin: dict, site_id: str) -> None:
    # Heading given (90°: east): the rotation is that heading; scale and drift are the
    # hypotheses the fit chose; every link says how it was placed.
    r = client.post("/v1/tracks", json=_track(site_id), headers=admin)
    result = _wait_done(client, admin, r.json()["track_id"])
    assert result["status"] == "done", result
    assert result["rotation"] == pytest.approx(90.0)
    assert 0.8 <= result["scale"] <= 1.2
    assert len(result["relaxed"]) == 14 and set(result["relaxed"]) <= {0, 1, 2, 3}
    assert result["spread"] >= 0 and result["anchors"] == 0
    assert isinstance(result["ambiguous"], bool)
    # the device's position carries the fit's own radius
    assert result["accuracy"] >= max(0.5, result["spread"])
    latest = client.get(f"/v1/devices/{site_id}-saver/position", headers=admin).json()
    assert latest["accuracy"] == result["accuracy"]
    best = result["candidates"][0]
    assert best["score"] == pytest.approx(result["score"], abs=1e-3)
    assert best["rotation"] == result["rotation"] and best["points"] is None


def test_withheld_heading_reports_the_runner_up(
    client: TestClient, admin: dict, site_id: str
) -> None:
    body = _track(site_id)
    del body["heading"]
    r = client.post("/v1/tracks", json=body, headers=admin)
    result = _wait_done(client, admin, r.json()["track_id"])
    assert result["status"] == "done", result
    assert 0.0 <= result["rotation"] < 360.0
    best, *others = result["candidates"]
    assert best["score"] == pytest.approx(result["score"], abs=1e-3)
    for other in others:
        assert other["score"] >= best["score"]
        # an ambiguous fit shows the runner-up's track too
        assert (other["points"] is not None) == result["ambiguous"]


def test_an_ambiguous_fits_radius_reaches_the_runner_ups_end() -> None:
    # 4 m straight from the middle of the open west room, heading withheld: the plan cannot
    # say which way the walker went, and the position the fit sets must not claim it knows
    segments = [
        {"t": T0 + 1000 * (i + 1), "length": 1.0, "turn": 0.0, "wifi": None} for i in range(4)
    ]
    request = {"start": {"x": 5.0, "y": 5.0}, "t0": T0, "segments": segments, "heading": None}
    job = {
        "site_id": "s",
        "floor_id": "G",
        "version": 1,
        "floor_doc": json.dumps(floor_doc()),
        "request": request,
        "radiomap": None,
        "cell": 0.25,
        "time_limit_s": 10.0,
    }
    result = run_fit(job)
    assert result["status"] == "done" and result["ambiguous"], result
    assert result["fitted"] is False and "rotation" in result["reason"]
    end, rival = result["points"][-1], result["candidates"][1]["points"][-1]
    gap = math.hypot(end["x"] - rival["x"], end["y"] - rival["y"])
    assert gap > 3.0 and result["accuracy"] >= gap - 1e-3


def test_scans_on_a_site_without_radio_maps_are_accepted_and_not_used(
    client: TestClient, admin: dict, site_id: str
) -> None:
    body = _track(site_id)
    body["segments"][5]["wifi"] = [{"id": "aa:bb:cc:dd:ee:01", "rssi": -60}]
    r = client.post("/v1/tracks", json=body, headers=admin)
    assert r.status_code == 202, r.text
    result = _wait_done(client, admin, r.json()["track_id"])
    assert result["status"] == "done" and result["anchors"] == 0
    bad = _track(site_id)
    bad["segments"][0]["wifi"] = [{"id": "aa:bb:cc:dd:ee:01", "rssi": 7}]
    assert client.post("/v1/tracks", json=bad, headers=admin).status_code == 422


def test_per_link_headings_are_validated_and_the_answer_says_whether_it_is_fitted(
    client: TestClient, admin: dict, site_id: str
) -> None:
    bad = _track(site_id)
    bad["segments"][3]["heading"] = 400.0
    r = client.post("/v1/tracks", json=bad, headers=admin)
    assert r.status_code == 422
    assert "heading" in json.dumps(r.json()["error"]["details"])
    r = client.post("/v1/tracks", json=_track(site_id, heading_sigma_deg=-1.0), headers=admin)
    assert r.status_code == 422 and "heading_sigma_deg" in r.text
    body = _track(site_id, heading=None, heading_sigma_deg=5.0)
    for s in body["segments"]:
        s["heading"] = 90.0
    r = client.post("/v1/tracks", json=body, headers=admin)
    assert r.status_code == 202, r.text
    result = _wait_done(client, admin, r.json()["track_id"])
    assert result["status"] == "done", result
    assert isinstance(result["fitted"], bool)
    assert result["fitted"] or result["reason"]
    radius = [p["radius"] for p in result["points"]]
    assert radius == sorted(radius) and radius[0] > 0
    assert result["bias"] is not None
