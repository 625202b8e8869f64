"""Surveys: recordings are stored with their counts; bad ones are rejected whole."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.datasets import data_dir
from app.datasets.ilc import fresh_wifi, read_walk, site_walks
from app.importers.ilc import survey_body
from app.surveys.models import SurveyRecord
from app.surveys.service import survey_samples

T0 = 1_700_000_000_000


def _survey(floor: str = "G") -> dict:
    return {
        "device_id": "surveyor",
        "floor_id": floor,
        "name": "corridor",
        "waypoints": [{"t": T0, "x": 1.0, "y": 8.0}, {"t": T0 + 10_000, "x": 9.0, "y": 8.0}],
        "wifi": [{"t": T0 + 500, "id": "aa:00:00:00:00:01", "rssi": -61, "freq": 2412}],
        "imu": [{"t": T0 + 20, "acc": [0.1, 0.2, 9.8], "rot": [0.0, 0.0, 0.1]}],
    }


def test_survey_is_stored_with_counts(client: TestClient, admin: dict, site_id: str) -> None:
    r = client.post(f"/v1/sites/{site_id}/surveys", json=_survey(), headers=admin)
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["counts"] == {
        "waypoints": 2,
        "wifi": 1,
        "ble": 0,
        "imu": 1,
        "uwb": 0,
        "uwb_fix": 0,
        "baro": 0,
    }
    with client.app.state.locus.sessions() as db:
        stored = survey_samples(db.get(SurveyRecord, body["id"]))
    assert stored["waypoints"][1] == {"t": T0 + 10_000, "x": 9.0, "y": 8.0}
    assert stored["wifi"][0]["rssi"] == -61
    listed = client.get(f"/v1/sites/{site_id}/surveys", headers=admin).json()
    assert [s["id"] for s in listed["items"]] == [body["id"]] and listed["total"] == 1


def test_a_survey_may_name_its_own_site_as_an_ingest_body_does(
    client: TestClient, admin: dict, site_id: str
) -> None:
    r = client.post(
        f"/v1/sites/{site_id}/surveys", json=_survey() | {"site_id": site_id}, headers=admin
    )
    assert r.status_code == 201, r.text
    with client.app.state.locus.sessions() as db:
        assert "site_id" not in survey_samples(db.get(SurveyRecord, r.json()["id"]))


def test_bad_surveys_are_rejected(client: TestClient, admin: dict, site_id: str) -> None:
    unordered = _survey()
    unordered["waypoints"].reverse()
    for body, status in (
        (_survey(floor="nope"), 404),
        (unordered, 422),
        (_survey() | {"waypoints": []}, 422),
    ):
        r = client.post(f"/v1/sites/{site_id}/surveys", json=body, headers=admin)
        assert r.status_code == status, r.text
    assert client.get(f"/v1/sites/{site_id}/surveys", headers=admin).json()["total"] == 0


def test_a_misconfigured_beacon_drops_its_field_not_the_survey(
    client: TestClient, admin: dict, site_id: str
) -> None:
    body = _survey()
    body["wifi"].append({"t": T0 + 900, "id": "aa:00:00:00:00:02", "rssi": 20})
    body["ble"] = [
        {"t": T0 + 700, "id": "bb:00:00:00:00:01", "rssi": -70, "tx_power": 86},
        {"t": T0 + 800, "id": "bb:00:00:00:00:02", "rssi": -75, "tx_power": -59},
    ]
    r = client.post(f"/v1/sites/{site_id}/surveys", json=body, headers=admin)
    assert r.status_code == 201, r.text
    answer = r.json()
    assert answer["counts"]["wifi"] == 1 and answer["counts"]["ble"] == 2
    assert [(d["kind"], d["index"], d["field"], d["dropped"]) for d in answer["dropped"]] == [
        ("wifi", 1, "rssi", "sample"),
        ("ble", 0, "tx_power", "field"),
    ]
    with client.app.state.locus.sessions() as db:
        stored = survey_samples(db.get(SurveyRecord, answer["id"]))
    assert "tx_power" not in stored["ble"][0] and stored["ble"][1]["tx_power"] == -59


DAY_MS = 24 * 3600 * 1000


def _survey_count(client: TestClient, admin: dict, site_id: str) -> int:
    return client.get(f"/v1/sites/{site_id}/surveys", headers=admin).json()["total"]


def test_a_survey_timed_in_seconds_is_refused_naming_the_unit(
    client: TestClient, admin: dict, site_id: str
) -> None:
    body = _survey()
    for item in (*body["waypoints"], *body["wifi"], *body["imu"]):
        item["t"] //= 1000
    r = client.post(f"/v1/sites/{site_id}/surveys", json=body, headers=admin)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "timestamp_units"
    assert error["message"].startswith("sample times look like seconds since the epoch")
    assert _survey_count(client, admin, site_id) == 0


def test_a_sample_far_from_the_survey_is_dropped_a_waypoint_refuses_it(
    client: TestClient, admin: dict, site_id: str
) -> None:
    body = _survey()
    body["wifi"] += [
        {"t": T0 + 900, "id": "aa:00:00:00:00:02", "rssi": 20},
        {"t": T0 + 10 * DAY_MS, "id": "aa:00:00:00:00:03", "rssi": -70},
    ]
    r = client.post(f"/v1/sites/{site_id}/surveys", json=body, headers=admin)
    assert r.status_code == 201, r.text
    answer = r.json()
    assert answer["counts"]["wifi"] == 1
    assert [(d["index"], d["field"], d["code"]) for d in answer["dropped"]] == [
        (1, "rssi", "less_than_equal"),
        (2, "t", "time_outlier"),
    ]
    late_waypoint = _survey()
    late_waypoint["waypoints"][1]["t"] += 10 * DAY_MS
    r = client.post(f"/v1/sites/{site_id}/surveys", json=late_waypoint, headers=admin)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "clock_skew"
    assert error["message"].startswith("waypoints[1]: t=")
    assert "is 10.0 days from the median time" in error["message"]
    assert error["details"][0]["loc"] == ["waypoints", 1, "t"]
    assert _survey_count(client, admin, site_id) == 1


def test_a_survey_walked_for_forty_minutes_is_kept_whole(
    client: TestClient, admin: dict, site_id: str
) -> None:
    minute = 60_000
    body = _survey() | {
        "waypoints": [{"t": T0 + 10 * minute * k, "x": 1.0 + 2 * k, "y": 8.0} for k in range(5)],
        "wifi": [
            {
                "t": T0 + minute * k,
                "id": "aa:00:00:00:00:01",
                "rssi": -61,
                "last_seen": T0 + minute * k - 1500,
            }
            for k in range(41)
        ],
    }
    r = client.post(f"/v1/sites/{site_id}/surveys", json=body, headers=admin)
    assert r.status_code == 201, r.text
    assert r.json()["dropped"] == [] and r.json()["counts"]["wifi"] == 41


SITE1 = data_dir() / "ilc" / "site1"


@pytest.mark.skipif(not SITE1.is_dir(), reason="ILC site1 recordings not present")
def test_a_real_site1_survey_keeps_all_but_its_two_impossible_values(
    client: TestClient, admin: dict, site_id: str
) -> None:
    _, path = site_walks(SITE1)[0]
    # readings timed by their own last-seen time: no staleness to drop
    body = survey_body(read_walk(path), device_id="surveyor", wifi_times="reading")
    body |= {"floor_id": "G"}
    assert len(body["ble"]) > 1 and len(body["wifi"]) > 1
    body["ble"][0]["tx_power"] = 86.0
    body["wifi"][1]["rssi"] = 20.0
    r = client.post(f"/v1/sites/{site_id}/surveys", json=body, headers=admin)
    assert r.status_code == 201, r.text
    answer = r.json()
    assert [(d["kind"], d["index"], d["field"], d["dropped"]) for d in answer["dropped"]] == [
        ("wifi", 1, "rssi", "sample"),
        ("ble", 0, "tx_power", "field"),
    ]
    assert answer["counts"]["wifi"] == len(body["wifi"]) - 1
    assert answer["counts"]["ble"] == len(body["ble"])


@pytest.mark.skipif(not SITE1.is_dir(), reason="ILC site1 recordings not present")
def test_a_survey_sent_as_android_reports_scans_keeps_only_fresh_readings(
    client: TestClient, admin: dict, site_id: str
) -> None:
    _, path = site_walks(SITE1)[0]
    walk = read_walk(path)
    scans = walk.wifi
    body = survey_body(walk, device_id="surveyor", wifi_times="scan") | {"floor_id": "G"}
    assert len(body["wifi"]) == len(scans) and all("last_seen" in s for s in body["wifi"])
    r = client.post(f"/v1/sites/{site_id}/surveys", json=body, headers=admin)
    assert r.status_code == 201, r.text
    answer = r.json()
    fresh = fresh_wifi(scans, Settings().wifi_max_age_ms)
    assert 0 < len(fresh) < len(scans)
    assert answer["counts"]["wifi"] == len(fresh)
    assert answer["dropped_total"] == len(scans) - len(fresh)
    assert {d["code"] for d in answer["dropped"]} == {"stale"}
