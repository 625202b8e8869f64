"""Sites are tenants: the same device id in two sites is two devices, each with its own
filter, history, stream and zone state, and no key of one site sees the other's."""

from __future__ import annotations

import uuid
from typing import Any

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from tests.conftest import ADMIN_KEY, floor_doc, make_key

T0 = 1_700_000_000_000
DEVICE = "tag-1"
"""The id every tenant picks."""


def _site(client: TestClient, admin: dict, doc: dict[str, Any]) -> str:
    sid = f"t-{uuid.uuid4().hex[:8]}"
    assert client.put(f"/v1/sites/{sid}", json={"name": sid}, headers=admin).status_code == 201
    assert client.put(f"/v1/sites/{sid}/floors/G", json=doc, headers=admin).status_code == 201
    return sid


def _warehouse() -> dict[str, Any]:
    """Return a 40 × 20 m floor, also named G, whose zone 'Dock' lies outside the office's
    outline (the office is 20 × 10 m with its zone 'Lab')."""
    doc = floor_doc()
    for feature in doc["features"]:
        kind = feature["properties"]["kind"]
        if kind == "outline":
            feature["geometry"]["coordinates"] = [[[0, 0], [40, 0], [40, 20], [0, 20], [0, 0]]]
        elif kind == "zone":
            feature["properties"]["name"] = "Dock"
            feature["geometry"]["coordinates"] = [
                [[30, 12], [34, 12], [34, 16], [30, 16], [30, 12]]
            ]
    return doc


def _walk(t0: int, x0: float, y: float, n: int) -> list[dict[str, Any]]:
    """Return UWB fixes of a tag walking east at 1 m/s from (x0, y), one each 200 ms."""
    return [
        {"t": t0 + 200 * k, "x": x0 + 0.2 * k, "y": y, "floor_id": "G", "std": 0.1}
        for k in range(n)
    ]


def _post(client: TestClient, key: dict, site: str, fixes: list[dict]) -> dict[str, Any]:
    body = {"device_id": DEVICE, "site_id": site, "uwb_fix": fixes}
    r = client.post("/v1/ingest?wait=true", json=body, headers=key)
    assert r.status_code == 200, r.text
    return r.json()


def test_the_same_device_id_in_two_sites_is_two_devices(
    client: TestClient, admin: dict[str, str]
) -> None:
    office, warehouse = _site(client, admin, floor_doc()), _site(client, admin, _warehouse())
    keys = {
        site: {role: make_key(client, admin, role, site) for role in ("device", "viewer")}
        for site in (office, warehouse)
    }
    # the office tag walks through its Lab (x 12…16 at y 4), the warehouse tag through its
    # Dock (x 30…34 at y 14); the warehouse's measurement times are older than the office's,
    # which a filter or late-sample count shared by the id would refuse as late
    office_walk, warehouse_walk = _walk(T0 + 600_000, 10.5, 4.0, 40), _walk(T0, 28.5, 14.0, 40)
    office_viewer, warehouse_viewer = keys[office]["viewer"], keys[warehouse]["viewer"]
    office_ws = f"/v1/ws/positions?site_id={office}&key={office_viewer['Authorization'][7:]}"
    warehouse_ws = f"/v1/ws/positions?key={warehouse_viewer['Authorization'][7:]}"
    with (
        client.websocket_connect(office_ws) as office_stream,
        client.websocket_connect(warehouse_ws) as warehouse_stream,
    ):
        answers: dict[str, list[dict]] = {office: [], warehouse: []}
        for half in (slice(0, 20), slice(20, 40)):  # the two tenants' uploads interleave
            answers[office].append(_post(client, keys[office]["device"], office, office_walk[half]))
            answers[warehouse].append(
                _post(client, keys[warehouse]["device"], warehouse, warehouse_walk[half])
            )
        # a last upload of each site after both walks: a stream that leaked the other
        # site's messages would show them before this one's
        for site, fix in ((office, office_walk[-1]), (warehouse, warehouse_walk[-1])):
            last = [fix | {"t": fix["t"] + 1000, "x": fix["x"] + 1.0}]
            answers[site].append(_post(client, keys[site]["device"], site, last))
        streamed: dict[str, list[dict]] = {office: [], warehouse: []}
        for site, stream in ((office, office_stream), (warehouse, warehouse_stream)):
            last_t = answers[site][-1]["positions"][-1]["t"]
            while not streamed[site] or streamed[site][-1].get("t") != last_t:
                streamed[site].append(stream.receive_json())

    for site, zone, xs in ((office, "Lab", (0, 20)), (warehouse, "Dock", (28, 40))):
        positions = [p for a in answers[site] for p in a["positions"]]
        assert all(a["late"] == 0 for a in answers[site]), "no sample of one site is late"
        assert len(positions) >= 30 and {p["site_id"] for p in positions} == {site}
        assert all(xs[0] <= p["x"] <= xs[1] for p in positions), "each filter on its own map"
        assert {m["site_id"] for m in streamed[site]} == {site}
        events = [(m["event"], m["zone"]) for m in streamed[site] if m["type"] == "zone"]
        assert events == [("enter", zone), ("exit", zone)]
        assert {p["t"] for p in positions} <= {m["t"] for m in streamed[site]}

    for site, other in ((office, warehouse), (warehouse, office)):
        viewer, device = keys[site]["viewer"], keys[site]["device"]
        own = f"/v1/sites/{site}/devices/{DEVICE}"
        history = client.get(own + "/positions?limit=10000", headers=viewer).json()["items"]
        assert history and {p["site_id"] for p in history} == {site}
        latest = client.get(own + "/position", headers=viewer).json()
        assert latest == answers[site][-1]["positions"][-1]
        # the older path reads the key's own site
        legacy = client.get(f"/v1/devices/{DEVICE}/positions?limit=10000", headers=viewer)
        assert legacy.json()["items"] == history
        listed = client.get(f"/v1/sites/{site}/devices", headers=viewer).json()
        assert [(d["device_id"], d["position"]["site_id"]) for d in listed["items"]] == [
            (DEVICE, site)
        ]
        theirs = f"/v1/sites/{other}/devices"
        for key in (viewer, device):
            for path in (theirs, f"{theirs}/{DEVICE}/position", f"{theirs}/{DEVICE}/positions"):
                r = client.get(path, headers=key)
                assert r.status_code == 403 and "items" not in r.json(), (path, r.text)
            r = client.get(f"/v1/devices/{DEVICE}/position?site_id={other}", headers=key)
            assert r.status_code == 403


def test_an_id_in_several_sites_needs_its_site_on_the_older_paths(
    client: TestClient, admin: dict[str, str]
) -> None:
    device = f"shared-{uuid.uuid4().hex[:6]}"
    sites = sorted(_site(client, admin, floor_doc()) for _ in range(2))
    for site in sites:
        body = {"device_id": device, "site_id": site, "uwb_fix": _walk(T0, 2.0, 2.0, 3)}
        assert client.post("/v1/ingest?wait=true", json=body, headers=admin).status_code == 200
    r = client.get(f"/v1/devices/{device}/position", headers=admin)
    assert r.status_code == 409
    assert r.json()["error"]["details"] == [{"sites": sites}]
    assert "?site_id=" in r.json()["error"]["message"]
    named = client.get(f"/v1/devices/{device}/positions?site_id={sites[1]}", headers=admin)
    assert named.status_code == 200 and {p["site_id"] for p in named.json()["items"]} == {sites[1]}
    unknown = client.get(f"/v1/devices/{device}-nowhere/position", headers=admin)
    assert unknown.status_code == 404


def test_device_listing_pages_and_says_when_each_was_last_heard(
    client: TestClient, admin: dict[str, str]
) -> None:
    site = _site(client, admin, floor_doc())
    for k in range(3):
        body = {"device_id": f"d{k}", "site_id": site, "uwb_fix": _walk(T0 + k, 2.0, 2.0, 2)}
        assert client.post("/v1/ingest?wait=true", json=body, headers=admin).status_code == 200
    first = client.get(f"/v1/sites/{site}/devices?limit=2", headers=admin).json()
    rest = client.get(f"/v1/sites/{site}/devices?limit=2&offset=2", headers=admin).json()
    assert first["total"] == 3 and [d["device_id"] for d in first["items"]] == ["d0", "d1"]
    assert [d["device_id"] for d in rest["items"]] == ["d2"]
    d2 = rest["items"][0]
    assert d2["last_t"] == T0 + 2 + 200 and d2["position"]["t"] == T0 + 2 + 200
    assert d2["last_seen"] >= d2["position"]["computed_at"] - 1000
    assert client.get("/v1/sites/no-such-site/devices", headers=admin).status_code == 404


def test_a_stream_filtered_by_device_needs_the_site_and_gets_only_that_device(
    client: TestClient, admin: dict[str, str]
) -> None:
    first, second = _site(client, admin, floor_doc()), _site(client, admin, floor_doc())
    with pytest.raises(WebSocketDisconnect) as closed:
        with client.websocket_connect(f"/v1/ws/positions?device_id={DEVICE}&key={ADMIN_KEY}"):
            pass
    assert closed.value.code == 1008 and "site_id is required" in closed.value.reason
    url = f"/v1/ws/positions?site_id={second}&device_id={DEVICE}&key={ADMIN_KEY}"
    with client.websocket_connect(url) as ws:
        for site in (first, second):
            _post(client, admin, site, _walk(T0, 2.0, 2.0, 6))
        message = ws.receive_json()
    assert (message["site_id"], message["device_id"]) == (second, DEVICE)
