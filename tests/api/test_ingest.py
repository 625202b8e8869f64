"""Ingest: accepted batches reach the device's filter; every malformed body gets the
documented 4xx and changes nothing."""

from __future__ import annotations

import json
import math
import time
import uuid
from typing import Any

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.core.config import Settings
from app.engine.wifi_age import DEFAULT_MAX_AGE_MS
from tests.conftest import ADMIN_KEY, floor_doc, make_key

T0 = 1_700_000_000_000
AP = ["aa:00:00:00:00:01", "aa:00:00:00:00:02", "aa:00:00:00:00:03"]


def batch(site: str, device: str, t0: int = T0, seconds: int = 3) -> dict:
    """Return a WiFi batch: one scan of the three APs per second."""
    wifi = [
        {"t": t0 + 1000 * s + 10 * i, "id": ap, "rssi": -50 - 5 * i}
        for s in range(seconds)
        for i, ap in enumerate(AP)
    ]
    return {"device_id": device, "site_id": site, "wifi": wifi}


def _bad_bodies(site: str) -> dict[str, tuple[str | bytes, int]]:
    good = batch(site, "bad-dev")
    far_future = int(time.time() * 1000) + 10 * 24 * 3600 * 1000
    huge = {
        "device_id": "bad-dev",
        "site_id": site,
        "wifi": [{"t": T0 + i, "id": AP[0], "rssi": -50} for i in range(10_001)],
    }
    loud = batch(site, "bad-dev")
    loud["wifi"][0]["rssi"] = "loud"
    fractional = batch(site, "bad-dev")
    fractional["wifi"][0]["t"] = T0 + 0.5
    return {
        "rssi as string": (json.dumps(loud), 422),
        "missing device_id": (json.dumps({k: v for k, v in good.items() if k != "device_id"}), 422),
        "every sample impossible": (json.dumps(good).replace('"rssi": -', '"rssi": '), 422),
        "float time": (json.dumps(fractional), 422),
        "time before 2000": (json.dumps(batch(site, "bad-dev", t0=1000)), 422),
        "far future time": (json.dumps(batch(site, "bad-dev", t0=far_future)), 422),
        "no samples": (json.dumps({"device_id": "bad-dev", "site_id": site}), 422),
        "imu vector of 2": (
            json.dumps(
                {"device_id": "bad-dev", "site_id": site, "imu": [{"t": T0, "acc": [1, 2]}]}
            ),
            422,
        ),
        "imu sample without fields": (
            json.dumps({"device_id": "bad-dev", "site_id": site, "imu": [{"t": T0}]}),
            422,
        ),
        "negative range": (
            json.dumps(
                {
                    "device_id": "bad-dev",
                    "site_id": site,
                    "uwb": [{"t": T0, "anchor": "A1", "range": -1}],
                }
            ),
            422,
        ),
        "unknown field": (json.dumps(good | {"gps": []}), 422),
        "not json": (b"{device_id: 1", 400),
        "too many samples": (json.dumps(huge), 413),
        "body over 1 MiB": (
            json.dumps(good | {"device_id": "x" * 10}).replace(
                '"wifi"', '"pad": "' + "x" * (1 << 20) + '", "wifi"'
            ),
            413,
        ),
        "unknown site": (json.dumps(batch("no-such-site", "bad-dev")), 404),
    }


@pytest.mark.parametrize("case", sorted(_bad_bodies("s")))
def test_malformed_batches_get_4xx_and_change_nothing(
    client: TestClient, admin: dict, site_id: str, case: str
) -> None:
    body, status = _bad_bodies(site_id)[case]
    r = client.post(
        "/v1/ingest?wait=true", content=body, headers=admin | {"content-type": "application/json"}
    )
    assert r.status_code == status, r.text
    assert set(r.json()["error"]) == {"code", "message", "details"}
    # nothing reached a filter: the device has no position at all
    assert client.get("/v1/devices/bad-dev/position", headers=admin).status_code == 404


def test_impossible_values_drop_only_their_sample_or_field(
    client: TestClient, admin: dict, site_id: str
) -> None:
    device = f"{site_id}-drops"
    body = batch(site_id, device)
    body["wifi"][1]["rssi"] = 20  # above 0 dBm: the sample goes
    body["wifi"][4]["tx_power"] = 86  # a misconfigured beacon: only the field goes
    raw = json.dumps(body).replace('"rssi": -60', '"rssi": NaN', 1)  # wifi[2]
    r = client.post(
        "/v1/ingest?wait=true", content=raw, headers=admin | {"content-type": "application/json"}
    )
    assert r.status_code == 200, r.text
    answer = r.json()
    assert answer["accepted"] == 7 and answer["dropped_total"] == 3
    assert [(d["index"], d["field"], d["dropped"]) for d in answer["dropped"]] == [
        (1, "rssi", "sample"),
        (2, "rssi", "sample"),
        (4, "tx_power", "field"),
    ]
    assert answer["dropped"][0]["code"] == "less_than_equal"
    assert "less than or equal to 0" in answer["dropped"][0]["reason"]
    assert answer["dropped"][1]["code"] == "finite_number"
    assert answer["positions"], "the sound samples were processed"
    metrics = client.get("/metrics", headers=admin).text
    assert 'locus_ingest_dropped_samples_total{kind="wifi",reason="finite_number"}' in metrics


def _aged_scan(site_id: str, device_id: str, ages_ms: list[int]) -> dict[str, Any]:
    """A batch of one WiFi scan whose i-th access point was last heard ``ages_ms[i]`` before
    the scan completed."""
    scan_t = T0 + 5000
    wifi = [
        {"t": scan_t, "id": AP[i], "rssi": -50 - 5 * i, "last_seen": scan_t - age}
        for i, age in enumerate(ages_ms)
    ]
    return {"device_id": device_id, "site_id": site_id, "wifi": wifi}


def test_cached_wifi_repeats_are_left_out_by_their_last_seen(
    client: TestClient, admin: dict, site_id: str
) -> None:
    body = _aged_scan(site_id, f"{site_id}-scan", [500, 12_000, 2000])
    r = client.post("/v1/ingest?wait=true", json=body, headers=admin)
    assert r.status_code == 200, r.text
    answer = r.json()
    assert answer["accepted"] == 2
    assert [(d["index"], d["code"], d["dropped"]) for d in answer["dropped"]] == [
        (1, "stale", "sample")
    ]
    # a batch of cached repeats only is sound: accepted with nothing to use, never refused
    everything_stale = body | {"wifi": [body["wifi"][1]]}
    r = client.post("/v1/ingest?wait=true", json=everything_stale, headers=admin)
    assert r.status_code == 200, r.text
    answer = r.json()
    assert answer["accepted"] == 0 and answer["positions"] == []
    assert [d["code"] for d in answer["dropped"]] == ["stale"]


def _stale_count(client: TestClient, admin: dict) -> float:
    for line in client.get("/metrics", headers=admin).text.splitlines():
        if line.startswith('locus_worker_samples_total{outcome="stale"}'):
            return float(line.split()[-1])
    return 0.0


def test_wifi_older_than_the_site_uses_is_accepted_and_counted_stale_by_the_workers(
    client: TestClient, admin: dict, site_id: str
) -> None:
    # no build: the site's engines use readings up to the default age, the ingest keeps
    # them up to its own cap; what lies between is accepted, left out, and counted
    assert DEFAULT_MAX_AGE_MS < Settings().wifi_max_age_ms
    body = _aged_scan(site_id, f"{site_id}-aged", [500, DEFAULT_MAX_AGE_MS + 1])
    before = _stale_count(client, admin)
    r = client.post("/v1/ingest?wait=true", json=body, headers=admin)
    assert r.status_code == 200, r.text
    assert r.json()["accepted"] == 2 and r.json()["dropped"] == []
    deadline = time.monotonic() + 10.0
    while _stale_count(client, admin) < before + 1 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _stale_count(client, admin) == before + 1


DAY_MS = 24 * 3600 * 1000
NOTHING_DROPPED = {"dropped": [], "dropped_total": 0}
"""What an answer says of drops when there were none."""


@pytest.mark.parametrize(
    ("unit", "scale"),
    [("seconds", 1e-3), ("microseconds", 1e3), ("nanoseconds", 1e6)],
)
@pytest.mark.parametrize("as_float", [False, True])
def test_times_in_another_unit_refuse_the_batch_naming_the_unit(
    client: TestClient, admin: dict, site_id: str, unit: str, scale: float, as_float: bool
) -> None:
    device = f"{site_id}-units"
    body = batch(site_id, device)
    for s in body["wifi"]:
        # time.time() in Python gives float seconds
        s["t"] = s["t"] * scale if as_float else int(s["t"] * scale)
    r = client.post("/v1/ingest?wait=true", json=body, headers=admin)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "timestamp_units"
    assert f"sample times look like {unit} since the epoch" in error["message"]
    assert "t must be milliseconds since the epoch" in error["message"]
    assert (
        client.get(f"/v1/sites/{site_id}/devices/{device}/position", headers=admin).status_code
        == 404
    )


def test_a_sample_far_from_its_batch_is_dropped_not_the_batch(
    client: TestClient, admin: dict, site_id: str
) -> None:
    body = batch(site_id, f"{site_id}-jump", seconds=17)
    body["wifi"] = body["wifi"][:50]
    body["wifi"][20]["t"] += 10 * DAY_MS
    r = client.post("/v1/ingest?wait=true", json=body, headers=admin)
    assert r.status_code == 200, r.text
    answer = r.json()
    assert answer["accepted"] == 49 and answer["dropped_total"] == 1
    (outlier,) = answer["dropped"]
    assert (outlier["kind"], outlier["index"], outlier["field"], outlier["dropped"]) == (
        "wifi",
        20,
        "t",
        "sample",
    )
    assert outlier["code"] == "time_outlier"
    assert "is 10.0 days from the median time" in outlier["reason"]
    assert "at most 1.0 hours" in outlier["reason"]
    assert answer["positions"] and max(p["t"] for p in answer["positions"]) < T0 + DAY_MS
    metrics = client.get("/metrics", headers=admin).text
    assert 'locus_ingest_dropped_samples_total{kind="wifi",reason="time_outlier"}' in metrics


def test_a_long_batch_of_old_scans_is_kept_whole(
    client: TestClient, admin: dict, site_id: str
) -> None:
    # a phone that buffered 50 minutes offline, uploading years later; readings last heard
    # a little before their scan
    wifi = [
        {"t": T0 + 60_000 * k, "id": ap, "rssi": -55, "last_seen": T0 + 60_000 * k - 1500}
        for k in range(50)
        for ap in AP
    ]
    body = {"device_id": f"{site_id}-buffered", "site_id": site_id, "wifi": wifi}
    r = client.post("/v1/ingest", json=body, headers=admin)
    assert r.status_code == 202, r.text
    assert r.json() == {"accepted": 150, "late": 0} | NOTHING_DROPPED


def test_wait_returns_positions_in_time_order(
    client: TestClient, admin: dict, site_id: str
) -> None:
    r = client.post("/v1/ingest?wait=true", json=batch(site_id, f"{site_id}-a"), headers=admin)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["accepted"] == 9 and body["late"] == 0
    ts = [p["t"] for p in body["positions"]]
    assert ts == sorted(ts) and len(ts) == 3
    assert all(p["floor_id"] == "G" and p["device_id"] == f"{site_id}-a" for p in body["positions"])


def test_unsorted_samples_are_ordered(client: TestClient, admin: dict, site_id: str) -> None:
    body = batch(site_id, f"{site_id}-u")
    body["wifi"].reverse()
    r = client.post("/v1/ingest?wait=true", json=body, headers=admin)
    assert [p["t"] for p in r.json()["positions"]] == [T0, T0 + 1000, T0 + 2000]


def test_late_samples_are_counted_not_used(client: TestClient, admin: dict, site_id: str) -> None:
    device = f"{site_id}-late"
    client.post("/v1/ingest?wait=true", json=batch(site_id, device, seconds=5), headers=admin)
    old = batch(site_id, device, seconds=2)
    r = client.post("/v1/ingest?wait=true", json=old, headers=admin)
    assert r.json() == {"accepted": 0, "late": 6, "positions": []} | NOTHING_DROPPED
    r = client.post("/v1/ingest", json=old, headers=admin)
    assert r.status_code == 202 and r.json() == {"accepted": 0, "late": 6} | NOTHING_DROPPED


def test_accepted_without_wait_is_processed(client: TestClient, admin: dict, site_id: str) -> None:
    device = f"{site_id}-async"
    r = client.post("/v1/ingest", json=batch(site_id, device), headers=admin)
    assert r.status_code == 202 and r.json() == {"accepted": 9, "late": 0} | NOTHING_DROPPED
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        # the reorder window holds the newest 2 s until the device goes quiet
        latest = client.get(f"/v1/devices/{device}/position", headers=admin)
        if latest.status_code == 200 and latest.json()["t"] == T0 + 2000:
            break
        time.sleep(0.1)
    assert latest.status_code == 200 and latest.json()["t"] == T0 + 2000


def test_history_is_ascending_and_paginated(client: TestClient, admin: dict, site_id: str) -> None:
    device = f"{site_id}-hist"
    client.post("/v1/ingest?wait=true", json=batch(site_id, device, seconds=7), headers=admin)
    page = client.get(f"/v1/devices/{device}/positions?limit=3", headers=admin).json()
    assert [p["t"] for p in page["items"]] == [T0, T0 + 1000, T0 + 2000]
    rest = client.get(
        f"/v1/devices/{device}/positions?limit=10&from={page['next_from']}", headers=admin
    ).json()
    assert [p["t"] for p in rest["items"]] == [T0 + 1000 * k for k in range(3, 7)]
    assert rest["next_from"] is None
    window = client.get(
        f"/v1/devices/{device}/positions?from={T0 + 1000}&to={T0 + 2000}", headers=admin
    ).json()
    assert [p["t"] for p in window["items"]] == [T0 + 1000, T0 + 2000]


def test_zone_events_on_entering_and_leaving(client: TestClient, admin: dict, site_id: str) -> None:
    device = f"{site_id}-zone"
    # a tag walking east at 1.25 m/s along y = 4 through the Lab zone (12 ≤ x ≤ 16): 3 s in
    # it and 3 s beyond it, each longer than the zone dwell time (2 s)
    fixes = [
        {"t": T0 + 200 * k, "x": 10.5 + 0.25 * k, "y": 4.0, "floor_id": "G", "std": 0.1}
        for k in range(38)
    ]
    url = f"/v1/ws/positions?site_id={site_id}&key={ADMIN_KEY}"
    with client.websocket_connect(url) as ws:
        r = client.post(
            "/v1/ingest?wait=true",
            json={"device_id": device, "site_id": site_id, "uwb_fix": fixes},
            headers=admin,
        )
        positions = r.json()["positions"]
        assert len(positions) >= 30 and all(p["method"] == "ekf" for p in positions)
        messages = [ws.receive_json() for _ in range(len(positions) + 2)]
    zone = [(m["event"], m["zone"]) for m in messages if m["type"] == "zone"]
    assert zone == [("enter", "Lab"), ("exit", "Lab")]
    # each reported at the crossing, not when the dwell confirmed it
    inside = [p for p in positions if 12 <= p["x"] <= 16]
    after = [p for p in positions if p["x"] > 16]
    events = {m["event"]: m["t"] for m in messages if m["type"] == "zone"}
    assert events == {"enter": inside[0]["t"], "exit": after[0]["t"]}


def test_a_device_jittering_at_a_doorway_gets_no_pair_shorter_than_the_dwell(
    client: TestClient, admin: dict, site_id: str
) -> None:
    device = f"{site_id}-door"
    # 6 s in the Lab's doorway (x = 12), a second on each side in turn, then 4 s inside the
    # Lab and 5 s back out by the wall
    xs = ([11.7] * 5 + [12.3] * 5) * 3 + [14.0] * 20 + [11.0] * 25
    fixes = [
        {"t": T0 + 200 * k, "x": x, "y": 4.0, "floor_id": "G", "std": 0.05}
        for k, x in enumerate(xs)
    ]
    url = f"/v1/ws/positions?site_id={site_id}&device_id={device}&key={ADMIN_KEY}"
    with client.websocket_connect(url) as ws:
        r = client.post(
            "/v1/ingest?wait=true",
            json={"device_id": device, "site_id": site_id, "uwb_fix": fixes},
            headers=admin,
        )
        positions = r.json()["positions"]
        messages = [ws.receive_json() for _ in range(len(positions) + 2)]
    # the engine's positions did cross the zone's edge back and forth in the doorway
    sides = [p["x"] >= 12 for p in positions if p["t"] < T0 + 6000]
    assert sum(a != b for a, b in zip(sides, sides[1:], strict=False)) >= 3
    zone = [m for m in messages if m["type"] == "zone"]
    assert [m["event"] for m in zone] == ["enter", "exit"]
    assert zone[1]["t"] - zone[0]["t"] >= 2000
    # the stay that lasted: entered in the doorway's last second, left after 10 s
    assert T0 + 5000 <= zone[0]["t"] <= T0 + 7000 and zone[1]["t"] >= T0 + 10_000


def test_locator_sightings_reach_the_tag(client: TestClient, admin: dict, site_id: str) -> None:
    r = client.post(
        "/v1/ingest/locator?wait=true",
        json={
            "site_id": site_id,
            "locator_id": "L1",
            "sightings": [{"t": T0, "tag_id": "tag-1", "rssi": -60}],
        },
        headers=admin,
    )
    # L1 is not on the map: the sighting is accepted but cannot produce a position
    assert r.status_code == 200 and r.json()["positions"] == []


def test_locators_reporting_the_same_moments_are_not_late(
    client: TestClient, admin: dict, site_id: str
) -> None:
    """Waiting on one locator's report must not close the tag's window to the others'."""
    tag = f"{site_id}-tag"
    for locator, times in (("L1", (T0 + 100, T0 + 900)), ("L2", (T0 + 50, T0 + 500))):
        body = {
            "site_id": site_id,
            "locator_id": locator,
            "sightings": [{"t": t, "tag_id": tag, "rssi": -60} for t in times],
        }
        r = client.post("/v1/ingest/locator?wait=true", json=body, headers=admin)
        assert r.status_code == 200 and r.json()["late"] == 0, r.text


def test_websocket_ingest_answers_each_message(client: TestClient, site_id: str) -> None:
    device = f"{site_id}-ws"
    with client.websocket_connect(f"/v1/ws/ingest?wait=true&key={ADMIN_KEY}") as ws:
        ws.send_text(json.dumps(batch(site_id, device)))
        answer = ws.receive_json()
        assert answer["accepted"] == 9 and len(answer["positions"]) == 3
        ws.send_text(json.dumps(batch(site_id, device) | {"wifi": []}))
        error = ws.receive_json()
        assert error["status"] == 422 and error["error"]["code"] == "invalid"
        ws.send_text(json.dumps(batch("no-such-site", device)))
        assert ws.receive_json()["status"] == 404


def test_websocket_ingest_needs_a_key(client: TestClient) -> None:
    with pytest.raises(WebSocketDisconnect) as closed:
        with client.websocket_connect("/v1/ws/ingest") as ws:
            ws.receive_json()
    assert closed.value.code == 1008


def test_transmitter_ids_match_in_any_case(client: TestClient, admin: dict) -> None:
    # iBeacon UUIDs and MAC addresses are hex: a map that writes them in capitals and a
    # phone that reports them in lower case (or the other way round) name the same beacons
    site = f"s-{uuid.uuid4().hex[:8]}"
    assert client.put(f"/v1/sites/{site}", json={"name": site}, headers=admin).status_code == 201
    doc = floor_doc()
    beacons = [
        ("ibeacon", "FDA50693-A4E2-4FB1-AFCF-C6EB07647825_10073_61418"),
        ("ble", "AA:BB:CC:00:00:02"),
        ("ibeacon", "fda50693-a4e2-4fb1-afcf-c6eb07647825_10073_61420"),
    ]
    transmitters = [f for f in doc["features"] if f["properties"]["kind"] == "transmitter"]
    for feature, (tech, ident) in zip(transmitters, beacons, strict=True):
        feature["properties"] |= {"tech": tech, "id": ident}
    assert client.put(f"/v1/sites/{site}/floors/G", json=doc, headers=admin).status_code == 201
    sent = [ident.swapcase() for _, ident in beacons]
    ble = [{"t": T0, "id": ident, "rssi": -60 - 5 * i} for i, ident in enumerate(sent)]
    body = {"device_id": "beacon-phone", "site_id": site, "ble": ble}
    r = client.post("/v1/ingest?wait=true", json=body, headers=admin)
    assert r.status_code == 200, r.text
    (position,) = r.json()["positions"]
    xy = [f["geometry"]["coordinates"][:2] for f in transmitters]
    # a weighted centroid of all three, not the one beacon whose id matched by case
    assert min(math.dist((position["x"], position["y"]), b) for b in xy) > 1.0, position


@pytest.mark.parametrize("route", ["/v1/ingest", "/v1/ingest/bulk"])
def test_ingest_answers_alike_however_its_query_is_spelt(
    client: TestClient, admin: dict, site_id: str, route: str
) -> None:
    def post(query: str, headers: dict, device: str) -> Any:
        body: dict = batch(site_id, f"{site_id}-{device}")
        if route.endswith("bulk"):
            body = {"batches": [body]}
        return client.post(route + query, json=body, headers=headers)

    for n, query in enumerate(["?wait=true", "?wait=1", "?wait=yes", "?wait=True"]):
        r = post(query, admin, f"q{n}")
        assert r.status_code == 200, (query, r.text)
    for n, query in enumerate(["", "?wait=false", "?wait=0", "?wait=no"]):
        assert post(query, admin, f"n{n}").status_code == 202, query
    r = post("?wait=true&site=x", admin, "unknown")
    assert r.status_code == 422 and "site" in r.json()["error"]["message"], r.text
    r = post("?wait=maybe", admin, "bad")
    assert r.status_code == 422 and "wait" in r.text, r.text
    for query in ("?wait=true", "?wait=yes"):
        r = post(query, {}, "anonymous")
        assert r.status_code == 401 and r.json()["error"]["code"] == "unauthorized", (query, r.text)


@pytest.mark.parametrize("route", ["/v1/ingest", "/v1/ingest/bulk", "/v1/ingest/locator"])
def test_plain_ingest_queries_are_answered_and_refused_as_any_other(
    client: TestClient, admin: dict, site_id: str, route: str
) -> None:
    """``?wait=true`` is served ahead of the framework's routing, ``?wait=True`` through it:
    every refusal must read the same either way, status, error object and headers."""
    viewer = make_key(client, admin, "viewer", site_id)
    too_long = b'{"device_id": "' + b"x" * (2 << 20) + b'"}'
    cases = {
        "no key": (b"{}", {}),
        "unknown key": (b"{}", {"Authorization": "Bearer lk_nope"}),
        "viewer key": (b"{}", viewer),
        "not json": (b"{device_id: 1", admin),
        "not a batch": (b'{"device_id": 3}', admin),
        "too large": (too_long, admin),
        "unknown site": (json.dumps(batch("no-such-site", "d")).encode(), admin),
    }
    for case, (body, headers) in cases.items():
        sent = headers | {"content-type": "application/json"}
        direct = client.post(route + "?wait=true", content=body, headers=sent)
        framework = client.post(route + "?wait=True", content=body, headers=sent)
        assert direct.status_code >= 400, (case, direct.text)
        assert direct.status_code == framework.status_code, (case, direct.text, framework.text)
        assert direct.json() == framework.json(), case
        assert direct.headers.get("retry-after") == framework.headers.get("retry-after"), case


def test_plain_ingest_requests_are_counted_by_their_route(
    client: TestClient, admin: dict, site_id: str
) -> None:
    def count() -> float:
        line = 'locus_http_requests_total{method="POST",route="/v1/ingest",status="202"}'
        found = [s for s in client.get("/metrics").text.splitlines() if s.startswith(line)]
        return float(found[0].rsplit(" ", 1)[1]) if found else 0.0

    before = count()
    for n in range(3):
        body = batch(site_id, f"{site_id}-counted-{n}")
        assert client.post("/v1/ingest", json=body, headers=admin).status_code == 202
    assert count() == before + 3
