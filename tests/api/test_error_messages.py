"""Mistakes a newcomer makes get an answer that names them: a body that is not JSON is a
400 on every endpoint, and a time in the wrong unit says that ``t`` is milliseconds."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

JSON = {"content-type": "application/json"}
T_S = 1_700_000_000
"""A time in seconds since the epoch, as Python's ``time.time()`` gives it."""


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("PUT", "/v1/sites/{site}"),
        ("POST", "/v1/keys"),
        ("POST", "/v1/ingest"),
        ("POST", "/v1/ingest/bulk"),
        ("POST", "/v1/ingest/locator"),
        ("POST", "/v1/tracks"),
        ("POST", "/v1/sites/{site}/surveys"),
        ("PUT", "/v1/sites/{site}/floors/G"),
    ],
)
def test_a_body_that_is_not_json_gets_400_naming_the_fault(
    client: TestClient, admin: dict, site_id: str, method: str, path: str
) -> None:
    r = client.request(
        method, path.format(site=site_id), content=b'{"name": "HQ",', headers=admin | JSON
    )
    assert r.status_code == 400, r.text
    error = r.json()["error"]
    assert error["code"] == "invalid_json"
    assert error["message"].startswith("body is not valid JSON: ")
    # the parser's reason follows: where the text stopped making sense
    assert len(error["message"]) > len("body is not valid JSON: ")


def _tracks(site: str, t0: int, step: int) -> tuple[str, dict]:
    return "/v1/tracks", {
        "device_id": "saver",
        "site_id": site,
        "floor_id": "G",
        "start": {"x": 2.0, "y": 8.5},
        "t0": t0,
        "segments": [{"t": t0 + step, "length": 1.0, "turn": 0.0}],
    }


def _locator(site: str, t0: int, step: int) -> tuple[str, dict]:
    sightings = [{"t": t0 + k * step, "tag_id": "tag", "rssi": -60} for k in range(3)]
    return "/v1/ingest/locator", {"site_id": site, "locator_id": "L1", "sightings": sightings}


def _ingest(site: str, t0: int, step: int) -> tuple[str, dict]:
    fixes = [{"t": t0 + k * step, "x": 2.0, "y": 5.0} for k in range(3)]
    return "/v1/ingest", {"device_id": "units", "site_id": site, "uwb_fix": fixes}


@pytest.mark.parametrize("body", [_tracks, _locator, _ingest])
@pytest.mark.parametrize(
    ("unit", "t0", "step"),
    [("seconds", T_S, 1), ("microseconds", T_S * 1_000_000, 1_000_000)],
)
def test_a_time_in_another_unit_says_t_is_milliseconds(
    client: TestClient, admin: dict, site_id: str, body, unit: str, t0: int, step: int
) -> None:
    path, doc = body(site_id, t0, step)
    r = client.post(path, json=doc, headers=admin)
    assert r.status_code == 422, r.text
    message = r.json()["error"]["message"]
    assert f"look like {unit} since the epoch" in message or f"looks like {unit}" in message
    assert "t must be milliseconds since the epoch" in message


def test_a_time_before_2000_says_why_it_is_refused(
    client: TestClient, admin: dict, site_id: str
) -> None:
    path, doc = _tracks(site_id, 1000, 1000)
    r = client.post(path, json=doc, headers=admin)
    assert r.status_code == 422, r.text
    message = r.json()["error"]["message"]
    assert "t0: t 1000 is before 2000-01-01" in message
    assert "milliseconds since the epoch" in message
