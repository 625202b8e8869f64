"""Every route in the OpenAPI document, and every WebSocket, asked by an admin and by a
viewer and a device key of site A for site B's resources: the keys of A get 403 (or 404
where they look in their own site), never B's data; the admin gets B's answer.

A route without an entry here fails the test, so a new endpoint must say who may use it.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import pytest
from fastapi.routing import APIWebSocketRoute
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from tests.conftest import floor_doc, make_key

T0 = 1_700_000_000_000
FIX = [{"t": T0, "x": 5.0, "y": 5.0, "floor_id": "G", "std": 0.1}]


@dataclass
class World:
    """Site B with a device, a track and a key of its own; keys of site A."""

    a: str
    b: str
    device: str
    track: str
    key_id: int
    admin: dict[str, str]
    viewer_a: dict[str, str]
    device_a: dict[str, str]


@pytest.fixture(scope="module")
def world(client: TestClient) -> World:
    from tests.conftest import ADMIN_KEY

    admin = {"Authorization": f"Bearer {ADMIN_KEY}"}
    a, b = f"ma-{uuid.uuid4().hex[:6]}", f"mb-{uuid.uuid4().hex[:6]}"
    for site in (a, b):
        assert client.put(f"/v1/sites/{site}", json={"name": site}, headers=admin).is_success
        assert client.put(f"/v1/sites/{site}/floors/G", json=floor_doc(), headers=admin).is_success
    device = f"{b}-only"
    body = {"device_id": device, "site_id": b, "uwb_fix": FIX}
    assert client.post("/v1/ingest?wait=true", json=body, headers=admin).json()["positions"]
    track = client.post("/v1/tracks", json=_track(b), headers=admin).json()["track_id"]
    client.post("/v1/keys", json={"role": "viewer", "site_id": b, "label": "b-key"}, headers=admin)
    keys = client.get(f"/v1/keys?site_id={b}", headers=admin).json()["items"]
    return World(
        a=a,
        b=b,
        device=device,
        track=track,
        key_id=keys[0]["id"],
        admin=admin,
        viewer_a=make_key(client, admin, "viewer", a),
        device_a=make_key(client, admin, "device", a),
    )


def _track(site: str) -> dict[str, Any]:
    return {
        "device_id": "walker",
        "site_id": site,
        "floor_id": "G",
        "start": {"x": 2, "y": 8},
        "t0": T0,
        "segments": [{"t": T0 + 1000, "length": 1, "turn": 0}],
    }


def _survey() -> dict[str, Any]:
    return {"device_id": "s", "floor_id": "G", "waypoints": [{"t": T0, "x": 1, "y": 1}]}


def _ingest(w: World) -> dict[str, Any]:
    return {"device_id": w.device, "site_id": w.b, "uwb_fix": FIX}


def _locator(w: World) -> dict[str, Any]:
    sighting = {"t": T0, "tag_id": w.device, "rssi": -60}
    return {"site_id": w.b, "locator_id": "L1", "sightings": [sighting]}


Check = Callable[[World, str, Any], None]
"""How a key of site A's answer is judged: (world, role, response)."""


def refused(status: int = 403) -> Check:
    """Return the check that the key of A got ``status`` with an error object, no data."""

    def check(w: World, role: str, r: Any) -> None:
        assert r.status_code == status, (role, r.status_code, r.text)
        assert set(r.json()) == {"error"}

    return check


def _no_b(w: World, role: str, r: Any) -> None:
    assert r.status_code in (200, 403), (role, r.text)
    assert w.b not in r.text


def _own_sites_only(w: World, role: str, r: Any) -> None:
    if role == "device":
        refused()(w, role, r)
    else:
        assert [s["id"] for s in r.json()["items"]] == [w.a]


def _bulk(w: World, role: str, r: Any) -> None:
    if role == "viewer":
        refused()(w, role, r)
    else:  # a device key may ingest, but each batch only for its own site
        assert r.status_code == 202
        assert [x["status"] for x in r.json()["results"]] == [403]


@dataclass
class Entry:
    """One route: the request against site B, the admin's status and the check of A's keys."""

    path: str
    body: Callable[[World], Any] | None = None
    admin: int = 200
    keys_of_a: Check = field(default_factory=refused)


MATRIX: dict[tuple[str, str], Entry] = {
    ("GET", "/healthz"): Entry("/healthz", keys_of_a=_no_b),
    ("GET", "/readyz"): Entry("/readyz", keys_of_a=_no_b),
    ("GET", "/metrics"): Entry("/metrics", keys_of_a=_no_b),
    ("GET", "/v1/keys/self"): Entry("/v1/keys/self", keys_of_a=_no_b),
    ("GET", "/v1/keys"): Entry("/v1/keys?site_id={b}"),
    ("POST", "/v1/keys"): Entry(
        "/v1/keys", lambda w: {"role": "viewer", "site_id": w.b}, admin=201
    ),
    ("DELETE", "/v1/keys/{key_id}"): Entry("/v1/keys/{key_id}", admin=204),
    ("GET", "/v1/sites"): Entry("/v1/sites?limit=1000", keys_of_a=_own_sites_only),
    ("GET", "/v1/sites/{site_id}"): Entry("/v1/sites/{b}"),
    ("PUT", "/v1/sites/{site_id}"): Entry("/v1/sites/{b}", lambda w: {"name": "B"}),
    ("GET", "/v1/sites/{site_id}/floors"): Entry("/v1/sites/{b}/floors"),
    ("GET", "/v1/sites/{site_id}/floors/{floor_id}"): Entry("/v1/sites/{b}/floors/G"),
    ("PUT", "/v1/sites/{site_id}/floors/{floor_id}"): Entry(
        "/v1/sites/{b}/floors/G", lambda w: floor_doc()
    ),
    ("GET", "/v1/sites/{site_id}/floors/{floor_id}/accuracy"): Entry(
        "/v1/sites/{b}/floors/G/accuracy?cell=2"
    ),
    ("GET", "/v1/sites/{site_id}/floors/{floor_id}/survey-guidance"): Entry(
        "/v1/sites/{b}/floors/G/survey-guidance", admin=404
    ),
    ("GET", "/v1/sites/{site_id}/floors/{floor_id}/heatmap"): Entry(
        "/v1/sites/{b}/floors/G/heatmap?from=0&to=86400000"
    ),
    ("GET", "/v1/sites/{site_id}/zones/{zone}/occupancy"): Entry(
        "/v1/sites/{b}/zones/Lab/occupancy?from=0&to=86400000"
    ),
    ("GET", "/v1/sites/{site_id}/positions"): Entry("/v1/sites/{b}/positions?from=0&to=86400000"),
    ("GET", "/v1/sites/{site_id}/devices"): Entry("/v1/sites/{b}/devices"),
    ("GET", "/v1/sites/{site_id}/devices/{device_id}/position"): Entry(
        "/v1/sites/{b}/devices/{device}/position"
    ),
    ("GET", "/v1/sites/{site_id}/devices/{device_id}/positions"): Entry(
        "/v1/sites/{b}/devices/{device}/positions"
    ),
    ("GET", "/v1/devices/{device_id}/position"): Entry("/v1/devices/{device}/position?site_id={b}"),
    ("GET", "/v1/devices/{device_id}/positions"): Entry(
        "/v1/devices/{device}/positions?site_id={b}"
    ),
    ("POST", "/v1/ingest"): Entry("/v1/ingest", _ingest, admin=202),
    ("POST", "/v1/ingest/bulk"): Entry(
        "/v1/ingest/bulk", lambda w: {"batches": [_ingest(w)]}, admin=202, keys_of_a=_bulk
    ),
    ("POST", "/v1/ingest/locator"): Entry("/v1/ingest/locator", _locator, admin=202),
    ("POST", "/v1/tracks"): Entry("/v1/tracks", lambda w: _track(w.b), admin=202),
    ("GET", "/v1/tracks/{track_id}"): Entry("/v1/tracks/{track}"),
    ("GET", "/v1/sites/{site_id}/radiomap"): Entry("/v1/sites/{b}/radiomap", admin=404),
    ("POST", "/v1/sites/{site_id}/radiomap/build"): Entry(
        "/v1/sites/{b}/radiomap/build", admin=409
    ),
    ("GET", "/v1/sites/{site_id}/radiomap/build/{job_id}"): Entry(
        "/v1/sites/{b}/radiomap/build/no-such-job", admin=404
    ),
    ("GET", "/v1/sites/{site_id}/surveys"): Entry("/v1/sites/{b}/surveys"),
    ("POST", "/v1/sites/{site_id}/surveys"): Entry(
        "/v1/sites/{b}/surveys", lambda w: _survey(), admin=201
    ),
    ("PUT", "/v1/sites/{site_id}/outputs/{output_id}"): Entry(
        "/v1/sites/{b}/outputs/hook",
        lambda w: {"kind": "webhook", "url": "http://127.0.0.1:9/", "secret": "s3cret-value"},
        admin=201,
    ),
    ("GET", "/v1/sites/{site_id}/outputs"): Entry("/v1/sites/{b}/outputs"),
    ("GET", "/v1/sites/{site_id}/outputs/{output_id}"): Entry("/v1/sites/{b}/outputs/hook"),
    ("DELETE", "/v1/sites/{site_id}/outputs/{output_id}"): Entry(
        "/v1/sites/{b}/outputs/hook", admin=204
    ),
    # last: they remove what the others read
    ("DELETE", "/v1/sites/{site_id}/floors/{floor_id}"): Entry("/v1/sites/{b}/floors/G", admin=204),
    ("DELETE", "/v1/sites/{site_id}"): Entry("/v1/sites/{b}", admin=204),
}


def test_every_route_has_an_entry(client: TestClient) -> None:
    document = client.get("/openapi.json").json()
    routes = {(method.upper(), path) for path, item in document["paths"].items() for method in item}
    assert routes == set(MATRIX)
    assert set(_websockets(client.app.routes)) == {"/v1/ws/positions", "/v1/ws/ingest"}


def _websockets(routes: list[Any]) -> list[str]:
    """Return the paths of the WebSocket routes, inside included routers too."""
    found = []
    for route in routes:
        if isinstance(route, APIWebSocketRoute):
            found.append(route.path)
        elif hasattr(route, "original_router"):
            found += _websockets(route.original_router.routes)
    return found


def _closed(client: TestClient, url: str) -> int:
    with pytest.raises(WebSocketDisconnect) as closed:
        with client.websocket_connect(url) as ws:
            ws.receive_json()
    return closed.value.code


def test_websockets_of_one_site_never_reach_another_site(client: TestClient, world: World) -> None:
    viewer, device = (k["Authorization"][7:] for k in (world.viewer_a, world.device_a))
    b, dev = world.b, world.device
    for key in (viewer, device):
        for query in (f"site_id={b}", f"site_id={b}&device_id={dev}", f"site_id={b}&floor_id=G"):
            assert _closed(client, f"/v1/ws/positions?{query}&key={key}") == 1008
    # a device key of A may stream ingest, but every message for B is refused
    with client.websocket_connect(f"/v1/ws/ingest?key={device}") as ws:
        ws.send_text(json.dumps(_ingest(world)))
        assert ws.receive_json()["status"] == 403
    with client.websocket_connect(f"/v1/ws/ingest?key={viewer}") as ws:
        ws.send_text(json.dumps(_ingest(world)))
        assert ws.receive_json()["status"] == 403
    admin = world.admin["Authorization"][7:]
    with client.websocket_connect(f"/v1/ws/positions?site_id={b}&key={admin}") as ws:
        body = {"device_id": dev, "site_id": b, "uwb_fix": [FIX[0] | {"t": T0 + 5000}]}
        client.post("/v1/ingest?wait=true", json=body, headers=world.admin)
        assert ws.receive_json()["site_id"] == b


def _request(client: TestClient, w: World, entry: Entry, method: str, headers: dict) -> Any:
    path = entry.path.format(b=w.b, device=w.device, track=w.track, key_id=w.key_id)
    body = None if entry.body is None else entry.body(w)
    return client.request(method, path, json=body, headers=headers)


def test_keys_of_one_site_never_reach_another_sites_data(client: TestClient, world: World) -> None:
    for (method, _), entry in MATRIX.items():
        for role, headers in (("viewer", world.viewer_a), ("device", world.device_a)):
            r = _request(client, world, entry, method, headers)
            entry.keys_of_a(world, role, r)
    # the older paths without a site read the key's own site, which has no such device
    for key in (world.viewer_a, world.device_a):
        r = client.get(f"/v1/devices/{world.device}/positions", headers=key)
        assert r.status_code in (403, 404) and set(r.json()) == {"error"}
    # and the admin, last (it deletes site B at the end), gets B's answers
    for (method, template), entry in MATRIX.items():
        r = _request(client, world, entry, method, world.admin)
        assert r.status_code == entry.admin, (method, template, r.status_code, r.text)


def test_unknown_query_parameters_are_refused_on_every_read(
    client: TestClient, admin: dict[str, str], site_id: str
) -> None:
    """A client that thinks it filters (``?site=``) learns that it did not: 422 naming it."""
    world = World(site_id, site_id, "nobody", "none", 0, admin, admin, admin)
    for (method, template), entry in MATRIX.items():
        if method != "GET":
            continue
        path = entry.path.format(b=site_id, device="nobody", track="none", key_id=0)
        joiner = "&" if "?" in path else "?"
        r = client.get(f"{path}{joiner}site=elsewhere", headers=world.admin)
        assert r.status_code == 422, (template, r.status_code, r.text)
        error = r.json()["error"]
        assert error["code"] == "unknown_query" and "site" in error["message"], template
        assert error["details"] == [
            {"loc": ["query", "site"], "msg": "unknown query parameter", "type": "extra_forbidden"}
        ]
    key = admin["Authorization"][7:]
    assert _closed(client, f"/v1/ws/positions?site={site_id}&key={key}") == 1008
