"""Every endpoint but /healthz needs a key (401); the wrong role or site gets 403."""

from __future__ import annotations

import hashlib

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.keys.models import ApiKey
from tests.conftest import floor_doc, make_key


def _ingest(site: str) -> dict:
    return {
        "device_id": "auth-dev",
        "site_id": site,
        "wifi": [{"t": 1_700_000_000_000, "id": "aa:00:00:00:00:01", "rssi": -50}],
    }


def _requests(site: str) -> list[tuple[str, str, dict | None]]:
    return [
        ("GET", "/v1/sites", None),
        ("GET", f"/v1/sites/{site}", None),
        ("PUT", f"/v1/sites/{site}", {"name": "x"}),
        ("DELETE", f"/v1/sites/{site}", None),
        ("GET", f"/v1/sites/{site}/floors", None),
        ("GET", f"/v1/sites/{site}/floors/G", None),
        ("PUT", f"/v1/sites/{site}/floors/G", floor_doc()),
        ("DELETE", f"/v1/sites/{site}/floors/G", None),
        ("POST", "/v1/keys", {"role": "viewer", "site_id": site}),
        ("POST", "/v1/ingest", _ingest(site)),
        (
            "POST",
            "/v1/ingest/locator",
            {
                "site_id": site,
                "locator_id": "L1",
                "sightings": [{"t": 1_700_000_000_000, "tag_id": "t", "rssi": -60}],
            },
        ),
        ("GET", "/v1/devices/auth-dev/position", None),
        ("GET", "/v1/devices/auth-dev/positions", None),
        ("GET", "/readyz", None),
        ("GET", "/metrics", None),
    ]


def test_healthz_needs_no_key(client: TestClient) -> None:
    r = client.get("/healthz")
    assert r.status_code == 200 and r.json()["status"] == "ok"


def test_every_endpoint_rejects_missing_and_unknown_keys(client: TestClient, site_id: str) -> None:
    for method, path, body in _requests(site_id):
        if path in ("/readyz", "/metrics"):
            continue
        r = client.request(method, path, json=body)
        assert r.status_code == 401, (method, path, r.text)
        assert r.json()["error"]["code"] == "unauthorized"
        r = client.request(method, path, json=body, headers={"Authorization": "Bearer nope"})
        assert r.status_code == 401, (method, path)


ADMIN_ONLY = {
    ("PUT", "/v1/sites/{s}"),
    ("DELETE", "/v1/sites/{s}"),
    ("PUT", "/v1/sites/{s}/floors/G"),
    ("DELETE", "/v1/sites/{s}/floors/G"),
    ("POST", "/v1/keys"),
}
DEVICE_ALLOWED = {("POST", "/v1/ingest"), ("POST", "/v1/ingest/locator")}


@pytest.mark.parametrize("role", ["device", "viewer"])
def test_roles_are_enforced(client: TestClient, admin: dict, site_id: str, role: str) -> None:
    headers = make_key(client, admin, role, site_id)
    for method, path, body in _requests(site_id):
        if path in ("/readyz", "/metrics") or path.startswith("/v1/devices"):
            continue
        template = (method, path.replace(site_id, "{s}"))
        forbidden = template in ADMIN_ONLY or ((role == "device") != (template in DEVICE_ALLOWED))
        r = client.request(method, path, json=body, headers=headers)
        if forbidden:
            assert r.status_code == 403, (role, method, path, r.status_code, r.text)
            assert r.json()["error"]["code"] == "forbidden"
        else:
            assert r.status_code in (200, 202), (role, method, path, r.status_code, r.text)


def test_keys_of_another_site_get_403(client: TestClient, admin: dict, site_id: str) -> None:
    other = f"{site_id}-other"
    assert client.put(f"/v1/sites/{other}", json={"name": "o"}, headers=admin).status_code == 201
    viewer = make_key(client, admin, "viewer", other)
    device = make_key(client, admin, "device", other)
    assert client.get(f"/v1/sites/{site_id}", headers=viewer).status_code == 403
    assert client.get(f"/v1/sites/{site_id}/floors/G", headers=viewer).status_code == 403
    assert client.post("/v1/ingest", json=_ingest(site_id), headers=device).status_code == 403
    listed = client.get("/v1/sites", headers=viewer).json()
    assert [s["id"] for s in listed["items"]] == [other]


def test_positions_are_readable_only_by_their_sites_viewers(
    client: TestClient, admin: dict, site_id: str
) -> None:
    body = _ingest(site_id) | {"device_id": f"{site_id}-dev"}
    r = client.post("/v1/ingest?wait=true", json=body, headers=admin)
    assert r.status_code == 200 and r.json()["positions"]
    own = make_key(client, admin, "viewer", site_id)
    client.put(f"/v1/sites/{site_id}-b", json={"name": "b"}, headers=admin)
    stranger = make_key(client, admin, "viewer", f"{site_id}-b")
    scoped = f"/v1/sites/{site_id}/devices/{site_id}-dev/position"
    assert client.get(scoped, headers=own).status_code == 200
    assert client.get(scoped, headers=stranger).status_code == 403
    assert client.get(scoped + "s", headers=stranger).status_code == 403
    # the older path reads the key's own site, where no such device is
    path = f"/v1/devices/{site_id}-dev/position"
    assert client.get(path, headers=own).status_code == 200
    assert client.get(path, headers=stranger).status_code == 404
    assert client.get(path + f"s?site_id={site_id}", headers=stranger).status_code == 403


def test_key_is_returned_once_and_stored_hashed(
    client: TestClient, admin: dict, site_id: str
) -> None:
    r = client.post(
        "/v1/keys",
        json={"role": "viewer", "site_id": site_id, "label": "wall screen"},
        headers=admin,
    )
    key = r.json()["key"]
    with client.app.state.locus.sessions() as db:
        stored = db.scalars(select(ApiKey.key_hash)).all()
    assert key not in stored
    assert hashlib.sha256(key.encode()).hexdigest() in stored


def test_scoped_keys_need_a_site(client: TestClient, admin: dict) -> None:
    r = client.post("/v1/keys", json={"role": "device"}, headers=admin)
    assert r.status_code == 422
    r = client.post("/v1/keys", json={"role": "device", "site_id": "no-such-site"}, headers=admin)
    assert r.status_code == 404


def test_keys_self_names_role_and_site(client: TestClient, admin: dict, site_id: str) -> None:
    assert client.get("/v1/keys/self", headers=admin).json() == {"role": "admin", "site_id": None}
    viewer = make_key(client, admin, "viewer", site_id)
    assert client.get("/v1/keys/self", headers=viewer).json() == {
        "role": "viewer",
        "site_id": site_id,
    }
    assert client.get("/v1/keys/self").status_code == 401


def test_surveys_tracks_and_planning_check_keys(
    client: TestClient, admin: dict, site_id: str
) -> None:
    survey = {
        "device_id": "d",
        "floor_id": "G",
        "waypoints": [{"t": 1_700_000_000_000, "x": 1, "y": 1}],
    }
    track = {
        "device_id": "d",
        "site_id": site_id,
        "floor_id": "G",
        "start": {"x": 2, "y": 8},
        "t0": 1_700_000_000_000,
        "segments": [{"t": 1_700_000_001_000, "length": 1, "turn": 0}],
    }
    calls = [
        ("POST", f"/v1/sites/{site_id}/surveys", survey),
        ("GET", f"/v1/sites/{site_id}/surveys", None),
        ("POST", "/v1/tracks", track),
        ("GET", f"/v1/sites/{site_id}/floors/G/accuracy", None),
    ]
    for method, path, body in calls:
        assert client.request(method, path, json=body).status_code == 401, path
    device = make_key(client, admin, "device", site_id)
    viewer = make_key(client, admin, "viewer", site_id)
    client.put(f"/v1/sites/{site_id}-x", json={"name": "x"}, headers=admin)
    stranger = make_key(client, admin, "device", f"{site_id}-x")
    assert client.post(calls[0][1], json=survey, headers=device).status_code == 403
    assert client.post(calls[0][1], json=survey, headers=viewer).status_code == 403
    assert client.get(calls[1][1], headers=device).status_code == 403
    assert client.get(calls[1][1], headers=viewer).status_code == 200
    assert client.post("/v1/tracks", json=track, headers=viewer).status_code == 403
    assert client.post("/v1/tracks", json=track, headers=stranger).status_code == 403
    accepted = client.post("/v1/tracks", json=track, headers=device)
    assert accepted.status_code == 202
    track_id = accepted.json()["track_id"]
    other_viewer = make_key(client, admin, "viewer", f"{site_id}-x")
    assert client.get(f"/v1/tracks/{track_id}", headers=other_viewer).status_code == 403
    assert client.get(f"/v1/tracks/{track_id}", headers=device).status_code == 200
    assert client.get(calls[3][1], headers=device).status_code == 403
    assert client.get(calls[3][1], headers=viewer).status_code == 200
