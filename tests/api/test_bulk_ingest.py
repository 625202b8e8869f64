"""Bulk ingest: a gateway's many devices in one body, each batch validated, authorised and
processed on its own and answered as the single ingest would answer it."""

from __future__ import annotations

import json
from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.conftest import make_key

T0 = 1_700_000_000_000
AP = ["aa:00:00:00:00:01", "aa:00:00:00:00:02", "aa:00:00:00:00:03"]


def batch(site: str, device: str, t0: int = T0, seconds: int = 3) -> dict[str, Any]:
    """Return a WiFi batch: one scan of the three APs per second."""
    wifi = [
        {"t": t0 + 1000 * s + 10 * i, "id": ap, "rssi": -50 - 5 * i}
        for s in range(seconds)
        for i, ap in enumerate(AP)
    ]
    return {"device_id": device, "site_id": site, "wifi": wifi}


def test_one_bad_batch_does_not_reject_the_others(
    client: TestClient, admin: dict, site_id: str
) -> None:
    bad = batch(site_id, f"{site_id}-bad")
    bad["wifi"][0]["rssi"] = "loud"
    batches = [
        batch(site_id, f"{site_id}-a"),
        bad,
        batch(site_id, f"{site_id}-b"),
        batch("no-such-site", f"{site_id}-c"),
        {"site_id": site_id, "wifi": []},
    ]
    r = client.post("/v1/ingest/bulk", json={"batches": batches}, headers=admin)
    assert r.status_code == 202, r.text
    results = r.json()["results"]
    assert [x["status"] for x in results] == [202, 422, 202, 404, 422]
    assert results[0] == {
        "status": 202,
        "accepted": 9,
        "late": 0,
        "dropped": [],
        "dropped_total": 0,
    }
    assert results[1]["error"]["code"] == "invalid"
    assert results[1]["error"]["details"][0]["loc"] == ["wifi", "0", "rssi"]
    assert "no-such-site" in results[3]["error"]["message"]
    assert {d["loc"][-1] for d in results[4]["error"]["details"]} >= {"device_id"}
    # the single ingest answers the bad batch exactly so
    single = client.post("/v1/ingest", json=bad, headers=admin).json()
    assert results[1]["error"] == single["error"]
    position = f"/v1/sites/{site_id}/devices/{site_id}-bad/position"
    assert client.get(position, headers=admin).status_code == 404, "the bad batch changed nothing"


def test_wait_answers_each_devices_positions(client: TestClient, admin: dict, site_id: str) -> None:
    devices = [f"{site_id}-w{k}" for k in range(3)]
    batches = [batch(site_id, d, t0=T0 + 100 * k) for k, d in enumerate(devices)]
    r = client.post("/v1/ingest/bulk?wait=true", json={"batches": batches}, headers=admin)
    assert r.status_code == 200, r.text
    for device, result in zip(devices, r.json()["results"], strict=True):
        assert result["status"] == 200 and result["accepted"] == 9
        ts = [p["t"] for p in result["positions"]]
        assert len(ts) == 3 and ts == sorted(ts)
        assert {p["device_id"] for p in result["positions"]} == {device}
        stored = client.get(f"/v1/sites/{site_id}/devices/{device}/positions", headers=admin)
        assert [p["t"] for p in stored.json()["items"]] == ts


def test_a_batchs_impossible_samples_are_dropped_and_reported_in_its_result(
    client: TestClient, admin: dict, site_id: str
) -> None:
    noisy = batch(site_id, f"{site_id}-noisy")
    noisy["wifi"][4]["rssi"] = 5
    batches = [batch(site_id, f"{site_id}-clean"), noisy]
    r = client.post("/v1/ingest/bulk?wait=true", json={"batches": batches}, headers=admin)
    clean, dropped = r.json()["results"]
    assert clean["dropped"] == [] and clean["dropped_total"] == 0 and clean["accepted"] == 9
    assert dropped["status"] == 200 and dropped["accepted"] == 8
    assert dropped["dropped_total"] == 1
    assert dropped["dropped"][0] | {"reason": ""} == {
        "kind": "wifi",
        "index": 4,
        "field": "rssi",
        "code": "less_than_equal",
        "reason": "",
        "dropped": "sample",
    }


def test_each_batch_is_authorised_for_its_own_site(
    client: TestClient, admin: dict, site_id: str
) -> None:
    other = f"{site_id}-o"
    assert client.put(f"/v1/sites/{other}", json={"name": "o"}, headers=admin).status_code == 201
    device = make_key(client, admin, "device", site_id)
    batches = [batch(site_id, f"{site_id}-mine"), batch(other, f"{site_id}-theirs")]
    r = client.post("/v1/ingest/bulk?wait=true", json={"batches": batches}, headers=device)
    mine, theirs = r.json()["results"]
    assert mine["status"] == 200 and mine["positions"]
    assert theirs["status"] == 403 and other in theirs["error"]["message"]
    assert "positions" not in theirs
    assert client.get(f"/v1/sites/{other}/devices", headers=admin).json()["total"] == 0
    viewer = make_key(client, admin, "viewer", site_id)
    refused = client.post("/v1/ingest/bulk", json={"batches": batches[:1]}, headers=viewer)
    assert refused.status_code == 403 and refused.json()["error"]["code"] == "forbidden"
    assert client.post("/v1/ingest/bulk", json={"batches": batches[:1]}).status_code == 401


def _samples(n: int, site: str) -> dict[str, Any]:
    return {
        "device_id": "many",
        "site_id": site,
        "wifi": [{"t": T0 + i, "id": AP[0], "rssi": -50} for i in range(n)],
    }


@pytest.mark.parametrize(
    ("name", "body", "status", "says"),
    [
        ("not JSON", b"{batches", 400, "not valid JSON"),
        ("not UTF-8", b'{"batches": [{"device_id": "\xff"}]}', 400, "not valid JSON"),
        ("an array cut short", b"[{}, ", 400, "not valid JSON"),
        ("no batches", json.dumps({"batch": []}).encode(), 422, '{"batches"'),
        ("batches not a list", json.dumps({"batches": {}}).encode(), 422, '{"batches"'),
        ("a list, not an object", json.dumps([{}]).encode(), 422, '{"batches"'),
        ("empty", json.dumps({"batches": []}).encode(), 422, "empty"),
        ("another field", json.dumps({"batches": [{}], "wait": True}).encode(), 422, "wait"),
        ("too many batches", json.dumps({"batches": [{}] * 1001}).encode(), 413, "1001 batches"),
    ],
)
def test_a_body_of_the_wrong_structure_is_refused_whole(
    client: TestClient, admin: dict, site_id: str, name: str, body: bytes, status: int, says: str
) -> None:
    headers = admin | {"content-type": "application/json"}
    r = client.post("/v1/ingest/bulk", content=body, headers=headers)
    assert r.status_code == status, (name, r.text)
    assert says in r.json()["error"]["message"]


def test_limits_scale_to_the_bulk_body_and_still_hold_per_batch(
    client: TestClient, admin: dict, site_id: str
) -> None:
    many = {"batches": [_samples(10_000, site_id)] * 10 + [_samples(1, site_id)]}
    r = client.post("/v1/ingest/bulk", json=many, headers=admin)
    assert r.status_code == 413 and "100001 samples" in r.json()["error"]["message"]
    one_too_big = {"batches": [_samples(10_001, site_id), batch(site_id, f"{site_id}-fine")]}
    r = client.post("/v1/ingest/bulk", json=one_too_big, headers=admin)
    assert [x["status"] for x in r.json()["results"]] == [413, 202]
    huge = b'{"batches": [' + b" " * (8 << 20) + b"]}"
    r = client.post("/v1/ingest/bulk", content=huge, headers=admin)
    assert r.status_code == 413
    position = f"/v1/sites/{site_id}/devices/many/position"
    assert client.get(position, headers=admin).status_code == 404, "refused bodies change nothing"


def test_unknown_query_parameters_are_refused(
    client: TestClient, admin: dict, site_id: str
) -> None:
    body = {"batches": [batch(site_id, f"{site_id}-q")]}
    r = client.post("/v1/ingest/bulk?wiat=true", json=body, headers=admin)
    assert r.status_code == 422 and "wiat" in r.json()["error"]["message"]


def test_each_batch_is_validated_from_the_bytes_the_client_sent(
    client: TestClient, admin: dict, site_id: str
) -> None:
    # pretty-printed, with a NaN literal (the json module reads it; msgspec does not) in one
    # batch and a sample list that is not a list in another: each answered as the single
    # ingest answers it, the NaN reading dropped, the others kept
    nan = batch(site_id, f"{site_id}-nan")
    nan["wifi"][1]["rssi"] = float("nan")
    odd = batch(site_id, f"{site_id}-odd") | {"ble": "none"}
    headers = admin | {"content-type": "application/json"}
    # a device of its own per body: a second batch of the same samples would be late
    for body in (
        json.dumps({"batches": [batch(site_id, f"{site_id}-fine-1"), odd]}, indent=2),
        json.dumps({"batches": [batch(site_id, f"{site_id}-fine-2"), odd, nan]}, indent=2),
    ):
        r = client.post("/v1/ingest/bulk", content=body.encode(), headers=headers)
        assert r.status_code == 202, r.text
        results = r.json()["results"]
        assert results[0]["accepted"] == 9
        single = client.post("/v1/ingest", content=json.dumps(odd), headers=headers).json()
        assert results[1]["status"] == 422
        assert results[1]["error"] == single["error"]
    assert results[2]["accepted"] == 8
    dropped = results[2]["dropped"][0]
    assert (dropped["kind"], dropped["index"], dropped["field"]) == ("wifi", 1, "rssi")
