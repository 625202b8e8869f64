"""Bad input of every kind a client sends, each with the answer it gets: the status and the
message that names the problem (the test ids list the kinds). None is a server error."""

from __future__ import annotations

import json
import uuid
from dataclasses import dataclass, field
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from tests.conftest import ADMIN_KEY, floor_doc, make_key

T0 = 1_700_000_000_000
AP = "aa:00:00:00:00:01"
SITE = "{site}"
"""Stands for the test's site in paths and bodies."""


@dataclass(frozen=True)
class Case:
    """A request (``key``: admin, device, viewer, other-device, none or a header value),
    the status it must get and a fragment of its message or details."""

    method: str
    path: str
    body: Any = None
    raw: bytes | None = None
    key: str = "admin"
    headers: dict[str, str] = field(default_factory=dict)
    status: int = 422
    says: str = ""


def _batch(**changes: Any) -> dict[str, Any]:
    body = {"device_id": "bad-1", "site_id": SITE, "wifi": [{"t": T0, "id": AP, "rssi": -50}]}
    return body | changes


def _survey(**changes: Any) -> dict[str, Any]:
    body = {
        "device_id": "s",
        "floor_id": "G",
        "waypoints": [{"t": T0, "x": 1, "y": 1}, {"t": T0 + 2000, "x": 2, "y": 1}],
        "wifi": [{"t": T0 + 10, "id": AP, "rssi": -50}],
    }
    return body | changes


def _locator(*sightings: dict[str, Any]) -> dict[str, Any]:
    return {"site_id": SITE, "locator_id": "L1", "sightings": list(sightings)}


def _open_ring() -> dict[str, Any]:
    doc = floor_doc()
    doc["features"][0]["geometry"]["coordinates"] = [[[0, 0], [20, 0], [20, 10]]]
    return doc


def _two_outlines() -> dict[str, Any]:
    doc = floor_doc()
    doc["features"].append(doc["features"][0])
    return doc


CASES: dict[str, Case] = {
    "ingest: body not JSON": Case(
        "POST", "/v1/ingest", raw=b"{device_id: x", status=400, says="JSON"
    ),
    "ingest: a JSON array": Case("POST", "/v1/ingest", raw=b"[1, 2]", says="object"),
    "ingest: no samples": Case(
        "POST", "/v1/ingest", {"device_id": "d", "site_id": SITE}, says="at least one sample"
    ),
    "ingest: RSSI as a word": Case(
        "POST", "/v1/ingest", _batch(wifi=[{"t": T0, "id": AP, "rssi": "loud"}]), says="number"
    ),
    "ingest: only sample above 0 dBm": Case(
        "POST",
        "/v1/ingest",
        _batch(wifi=[{"t": T0, "id": AP, "rssi": 7}]),
        says="every sample was dropped",
    ),
    "ingest: one sample NaN, one sound": Case(
        "POST",
        "/v1/ingest",
        _batch(wifi=[{"t": T0, "id": AP, "rssi": "NaN"}, {"t": T0, "id": "b", "rssi": -60}]),
        status=202,
        says="finite_number",
    ),
    "ingest: an imu sample whose only sensor is NaN, one sound": Case(
        "POST",
        "/v1/ingest",
        _batch(imu=[{"t": T0, "acc": [1, 2, "NaN"]}, {"t": T0 + 20, "acc": [0.1, 0.2, 9.8]}]),
        status=202,
        says="finite_number",
    ),
    "ingest: only cached WiFi, last heard 12 s before its scan": Case(
        "POST",
        "/v1/ingest",
        _batch(wifi=[{"t": T0, "id": AP, "rssi": -50, "last_seen": T0 - 12_000}]),
        status=202,
        says="stale",
    ),
    "ingest: times in seconds": Case(
        "POST",
        "/v1/ingest",
        _batch(wifi=[{"t": T0 // 1000, "id": AP, "rssi": -50}]),
        says="seconds since the epoch",
    ),  # fmt: skip
    "ingest: a sample an hour off": Case(
        "POST",
        "/v1/ingest",
        _batch(
            wifi=[{"t": T0 + k, "id": AP, "rssi": -50} for k in range(3)]
            + [{"t": T0 + 7_200_000, "id": AP, "rssi": -50}]
        ),
        status=202,
        says="time_outlier",
    ),
    "ingest: time as a float": Case(
        "POST",
        "/v1/ingest",
        _batch(wifi=[{"t": T0 + 0.5, "id": AP, "rssi": -50}]),
        says="integer",
    ),  # fmt: skip
    "ingest: t beyond 64 bits": Case(
        "POST", "/v1/ingest", _batch(wifi=[{"t": 2**70, "id": AP, "rssi": -50}]), says="t"
    ),
    "ingest: unknown field": Case("POST", "/v1/ingest", _batch(gps=[]), says="Extra inputs"),
    "ingest: device id with a slash": Case(
        "POST", "/v1/ingest", _batch(device_id="a/b"), says="pattern"
    ),
    "ingest: over 10,000 samples": Case(
        "POST",
        "/v1/ingest",
        _batch(wifi=[{"t": T0 + k, "id": AP, "rssi": -50} for k in range(10_001)]),
        status=413,
        says="limit is 10000",
    ),  # fmt: skip
    "ingest: body over 1 MiB": Case(
        "POST", "/v1/ingest", raw=b" " * (1024 * 1024 + 1), status=413, says="larger than"
    ),
    "ingest: unknown site": Case(
        "POST", "/v1/ingest", _batch(site_id="nowhere-17"), status=404, says="not found"
    ),
    "ingest: no key": Case("POST", "/v1/ingest", _batch(), key="none", status=401, says="missing"),
    "ingest: Basic auth": Case(
        "POST", "/v1/ingest", _batch(), key="Basic dXNlcjpwYXNz", status=401, says="Basic"
    ),
    "ingest: unknown key": Case(
        "POST", "/v1/ingest", _batch(), key="Bearer lk_nobody", status=401, says="unknown API key"
    ),
    "ingest: viewer key, broken body": Case(
        "POST", "/v1/ingest", raw=b"{", key="viewer", status=403, says="device and admin"
    ),
    "ingest: device key of another site": Case(
        "POST", "/v1/ingest", _batch(), key="other-device", status=403, says="may not report"
    ),
    "ingest: misspelt query parameter": Case("POST", "/v1/ingest?wiat=true", _batch(), says="wiat"),
    "ingest: wrong method": Case("GET", "/v1/ingest", status=405, says="use POST"),
    "bulk: batches not a list": Case("POST", "/v1/ingest/bulk", {"batches": {}}, says="batches"),
    "bulk: no batches": Case("POST", "/v1/ingest/bulk", {"batches": []}, says="batches"),
    "locator: sighting without RSSI": Case(
        "POST", "/v1/ingest/locator", _locator({"t": T0, "tag_id": "t"}), says="rssi"
    ),
    "locator: one sighting above 0 dBm, one sound": Case(
        "POST",
        "/v1/ingest/locator",
        _locator({"t": T0, "tag_id": "t", "rssi": 7}, {"t": T0 + 100, "tag_id": "t", "rssi": -70}),
        status=202,
        says="less_than_equal",
    ),
    "locator: only sighting above 0 dBm": Case(
        "POST",
        "/v1/ingest/locator",
        _locator({"t": T0, "tag_id": "t", "rssi": 7}),
        says="every sample was dropped",
    ),
    "site: id with a space": Case("PUT", "/v1/sites/a%20b", {"name": "x"}, says="pattern"),
    "site: no name": Case("PUT", "/v1/sites/bad-site-17", {}, says="name"),
    "site: name not JSON (text/plain)": Case(
        "PUT",
        "/v1/sites/bad-site-17",
        raw=b"name=x",
        headers={"content-type": "text/plain"},
        says="valid dictionary",
    ),  # fmt: skip
    "floor: not a FeatureCollection": Case(
        "PUT", f"/v1/sites/{SITE}/floors/X", {"type": "Feature"}, says="FeatureCollection"
    ),
    "floor: unclosed polygon ring": Case(
        "PUT", f"/v1/sites/{SITE}/floors/X", _open_ring(), says="must be closed"
    ),
    "floor: two outlines": Case(
        "PUT", f"/v1/sites/{SITE}/floors/X", _two_outlines(), says="exactly one outline"
    ),
    "floor: NaN coordinate": Case(
        "PUT",
        f"/v1/sites/{SITE}/floors/X",
        raw=json.dumps(floor_doc()).replace("[20, 10]", "[NaN, 10]", 1).encode(),
        says="finite",
    ),  # fmt: skip
    "floor: of an unknown site": Case(
        "PUT", "/v1/sites/nowhere-17/floors/X", floor_doc(), status=404, says="not found"
    ),
    "key: unknown role": Case("POST", "/v1/keys", {"role": "superuser"}, says="role"),
    "key: device key without a site": Case("POST", "/v1/keys", {"role": "device"}, says="site"),
    "history: negative limit": Case(
        "GET", f"/v1/sites/{SITE}/devices/d/positions?limit=-1", says="limit"
    ),
    "history: from as a word": Case(
        "GET", f"/v1/sites/{SITE}/devices/d/positions?from=yesterday", says="from"
    ),
    "track: no segments": Case(
        "POST",
        "/v1/tracks",
        {
            "device_id": "d",
            "site_id": SITE,
            "floor_id": "G",
            "start": {"x": 1, "y": 1},
            "t0": T0,
            "segments": [],
        },
        says="segments",
    ),  # fmt: skip
    "survey: waypoint an hour off": Case(
        "POST",
        f"/v1/sites/{SITE}/surveys",
        _survey(waypoints=[{"t": T0, "x": 1, "y": 1}, {"t": T0 + 7_200_000, "x": 2, "y": 1}]),
        says="clock_skew",
    ),
    "survey: names another site": Case(
        "POST", f"/v1/sites/{SITE}/surveys", _survey(site_id="elsewhere"), says="posted to site"
    ),
    "planning: unknown tech": Case(
        "GET", f"/v1/sites/{SITE}/floors/G/accuracy?tech=laser", says="tech"
    ),
    "unknown path": Case("GET", "/v1/nothing-here", status=404, says="Not Found"),
}


def _fill(value: Any, site: str) -> Any:
    return json.loads(json.dumps(value).replace(SITE, site)) if value is not None else None


@dataclass(frozen=True)
class Setting:
    """A site with the test floor, and the headers of each kind of key."""

    site_id: str
    keys: dict[str, dict[str, str]]


@pytest.fixture(scope="module")
def setting(client: TestClient) -> Setting:
    """A site of its own with the test floor, its device and viewer keys and another site's."""
    admin = {"Authorization": f"Bearer {ADMIN_KEY}"}
    site, other = f"bad-{uuid.uuid4().hex[:6]}", f"bad-other-{uuid.uuid4().hex[:6]}"
    for sid in (site, other):
        assert client.put(f"/v1/sites/{sid}", json={"name": sid}, headers=admin).is_success
    assert client.put(f"/v1/sites/{site}/floors/G", json=floor_doc(), headers=admin).is_success
    keys = {
        "admin": admin,
        "device": make_key(client, admin, "device", site),
        "viewer": make_key(client, admin, "viewer", site),
        "other-device": make_key(client, admin, "device", other),
        "none": {},
    }
    return Setting(site, keys)


def send(client: TestClient, setting: Setting, case: Case) -> httpx.Response:
    """Send the case's request in the setting."""
    headers = dict(setting.keys.get(case.key, {"Authorization": case.key})) | case.headers
    kwargs: dict[str, Any] = {"headers": headers}
    if case.raw is not None:
        headers.setdefault("content-type", "application/json")
        kwargs["content"] = case.raw
    elif case.body is not None:
        kwargs["json"] = _fill(case.body, setting.site_id)
    return client.request(case.method, case.path.replace(SITE, setting.site_id), **kwargs)


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_gets_the_status_and_message_that_name_the_problem(
    name: str, client: TestClient, setting: Setting
) -> None:
    case = CASES[name]
    r = send(client, setting, case)
    assert r.status_code == case.status, r.text
    assert case.says in r.text, r.text
    if case.status >= 400:
        assert set(r.json()) == {"error"} and r.json()["error"]["message"], r.text
