"""Floor maps: stored and returned as uploaded; every bad map gets a 422 naming the
feature and reason, and leaves what was stored untouched."""

from __future__ import annotations

import copy
import json
from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.conftest import floor_doc


def _feature(kind: str, geometry: dict, **props: Any) -> dict:
    return {"type": "Feature", "geometry": geometry, "properties": {"kind": kind, **props}}


SQUARE = {"type": "Polygon", "coordinates": [[[2, 2], [4, 2], [4, 4], [2, 4], [2, 2]]]}
BOWTIE = {"type": "Polygon", "coordinates": [[[0, 0], [4, 4], [4, 0], [0, 4], [0, 0]]]}


def _with(feature: dict) -> dict:
    doc = floor_doc()
    doc["features"].append(feature)
    return doc


BAD_MAPS: dict[str, tuple[dict, int | None, str]] = {
    "self-intersecting barrier": (_with(_feature("barrier", BOWTIE)), 6, "invalid geometry"),
    "wall given as polygon": (_with(_feature("wall", SQUARE)), 6, "geometry must be"),
    "unknown kind": (_with(_feature("stairs", SQUARE)), 6, "'kind' must be one of"),
    "transmitter without id": (
        _with(_feature("transmitter", {"type": "Point", "coordinates": [1, 2]}, tech="wifi")),
        6,
        "'id'",
    ),
    "transmitter with unknown tech": (
        _with(
            _feature("transmitter", {"type": "Point", "coordinates": [1, 2]}, id="x1", tech="lora")
        ),
        6,
        "'tech'",
    ),
    "anchor without height": (
        _with(_feature("anchor", {"type": "Point", "coordinates": [1, 2]}, id="A9")),
        6,
        "[x, y, z]",
    ),
    "duplicate transmitter id": (
        _with(
            _feature(
                "transmitter",
                {"type": "Point", "coordinates": [3, 3]},
                id="AA:00:00:00:00:01",
                tech="wifi",
            )
        ),
        6,
        "repeats feature 3",
    ),
    "non-finite coordinate": (
        _with(_feature("locator", {"type": "Point", "coordinates": [1, 2, 1e400]}, id="L1")),
        6,
        "finite",
    ),
    "negative attenuation": (
        _with(
            _feature(
                "transmitter",
                {"type": "Point", "coordinates": [3, 3]},
                id="bb:00:00:00:00:09",
                tech="ble",
                B=-2,
            )
        ),
        6,
        "'B' must be positive",
    ),
    "zone without name": (_with(_feature("zone", SQUARE)), 6, "'name'"),
    "second outline": (_with(_feature("outline", SQUARE)), None, "exactly one outline"),
}


def _state(client: TestClient, site: str, admin: dict) -> tuple[Any, Any]:
    floors = client.get(f"/v1/sites/{site}/floors", headers=admin).json()
    doc = client.get(f"/v1/sites/{site}/floors/G", headers=admin).json()
    return floors, doc


@pytest.mark.parametrize("case", sorted(BAD_MAPS))
def test_bad_map_is_rejected_with_feature_and_reason(
    client: TestClient, admin: dict, site_id: str, case: str
) -> None:
    doc, index, reason = BAD_MAPS[case]
    before = _state(client, site_id, admin)
    # allow_nan: the non-finite case sends the literal Infinity some encoders emit
    body = json.dumps(doc, allow_nan=True)
    r = client.put(f"/v1/sites/{site_id}/floors/G", content=body, headers=admin)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "invalid_floor_map"
    assert any(d["index"] == index and reason in d["reason"] for d in error["details"]), error
    # a new floor id is not created by a rejected upload either
    assert (
        client.put(f"/v1/sites/{site_id}/floors/NEW", content=body, headers=admin).status_code
        == 422
    )
    assert _state(client, site_id, admin) == before
    assert client.get(f"/v1/sites/{site_id}/floors/NEW", headers=admin).status_code == 404


def test_every_problem_is_listed_at_once(client: TestClient, admin: dict, site_id: str) -> None:
    doc = floor_doc()
    doc["features"] += [_feature("barrier", BOWTIE), _feature("wall", SQUARE)]
    doc["properties"]["level"] = "ground"
    r = client.put(f"/v1/sites/{site_id}/floors/G", json=doc, headers=admin)
    details = r.json()["error"]["details"]
    assert {(d["index"], d["kind"]) for d in details} == {(None, None), (6, "barrier"), (7, "wall")}


def test_not_geojson_is_rejected(client: TestClient, admin: dict, site_id: str) -> None:
    r = client.put(f"/v1/sites/{site_id}/floors/G", content=b"{not json", headers=admin)
    assert r.status_code == 400
    r = client.put(f"/v1/sites/{site_id}/floors/G", json={"type": "Feature"}, headers=admin)
    assert r.status_code == 422


def test_floor_roundtrip_and_summary(client: TestClient, admin: dict, site_id: str) -> None:
    doc = floor_doc()
    doc["features"].append(_feature("barrier", SQUARE))
    r = client.put(f"/v1/sites/{site_id}/floors/G", json=doc, headers=admin)
    assert r.status_code == 200
    summary = r.json()
    assert summary["bounds"] == [0.0, 0.0, 20.0, 10.0]
    assert summary["walkable_area"] == pytest.approx(200.0 - 4.0)
    assert summary["counts"] == {
        "wall": 1,
        "barrier": 1,
        "room": 0,
        "zone": 1,
        "transmitter": 3,
        "anchor": 0,
        "locator": 0,
    }
    assert client.get(f"/v1/sites/{site_id}/floors/G", headers=admin).json() == doc
    listed = client.get(f"/v1/sites/{site_id}/floors", headers=admin).json()
    assert [f["floor_id"] for f in listed] == ["G"]


def test_floor_of_unknown_site_is_404(client: TestClient, admin: dict) -> None:
    r = client.put("/v1/sites/nowhere/floors/G", json=floor_doc(), headers=admin)
    assert r.status_code == 404
    assert r.json()["error"]["code"] == "not_found"


def test_site_delete_removes_its_floors(client: TestClient, admin: dict, site_id: str) -> None:
    assert client.delete(f"/v1/sites/{site_id}", headers=admin).status_code == 204
    assert client.get(f"/v1/sites/{site_id}", headers=admin).status_code == 404
    assert client.get(f"/v1/sites/{site_id}/floors/G", headers=admin).status_code == 404


def test_site_update_keeps_floors(client: TestClient, admin: dict, site_id: str) -> None:
    r = client.put(
        f"/v1/sites/{site_id}", json={"name": "Renamed", "config": {"engine": "hmm"}}, headers=admin
    )
    assert r.status_code == 200 and r.json()["name"] == "Renamed"
    assert r.json()["config"] == {"engine": "hmm"}
    assert client.get(f"/v1/sites/{site_id}/floors/G", headers=admin).status_code == 200
    doc = copy.deepcopy(floor_doc())
    assert client.put(f"/v1/sites/{site_id}/floors/G", json=doc, headers=admin).status_code == 200


def _outline(ring: list[list[float]]) -> dict:
    doc = floor_doc()
    doc["features"][0]["geometry"] = {"type": "Polygon", "coordinates": [ring]}
    return doc


def _box(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]


FAR_WALL = _feature("wall", {"type": "LineString", "coordinates": [[5, 5], [90_000, 5]]})

# A map in the wrong unit or of the wrong size: each named at its feature, never a 500.
MISTAKES: dict[str, tuple[dict, int | None, tuple[str, ...]]] = {
    "outline in degrees": (
        _outline(_box(13.4050, 52.5200, 13.4056, 52.5203)),
        0,
        ("look like longitude/latitude degrees", "floor maps are in metres", "'georef'"),
    ),
    "outline 100 km across": (
        _outline(_box(0, 0, 100_000, 100_000)),
        0,
        ("100,000 m × 100,000 m", "larger than the limit of 3,000 m", "LOCUS_FLOOR_MAX_EXTENT_M"),
    ),
    "outline over the raster budget": (
        _outline(_box(0, 0, 1500, 1500)),
        0,
        ("raster cells of 0.25 m", "LOCUS_FLOOR_MAX_RASTER_CELLS"),
    ),
    "outline of a few centimetres": (
        _outline(_box(0, 0, 0.4, 0.2)),
        0,
        ("only 0.4 m × 0.2 m across", "in metres"),
    ),
    "outline thinner than a raster cell": (
        _outline(_box(0, 0, 20, 0.1)),
        None,
        ("covers no raster cell of 0.25 m",),
    ),
    "wall 90 km away": (_with(FAR_WALL), 6, ("90,000", "LOCUS_FLOOR_MAX_EXTENT_M")),
    "self-intersecting outline": (
        _outline([[0, 0], [30, 0], [0, 20], [30, 20], [0, 0]]),
        0,
        ("invalid geometry: its edges cross each other at (15, 10)",),
    ),
}


@pytest.mark.parametrize("case", sorted(MISTAKES))
def test_a_map_of_the_wrong_unit_or_size_is_named_as_such(
    client: TestClient, admin: dict, site_id: str, case: str
) -> None:
    doc, index, says = MISTAKES[case]
    before = _state(client, site_id, admin)
    r = client.put(f"/v1/sites/{site_id}/floors/G", json=doc, headers=admin)
    assert r.status_code == 422, r.text
    details = r.json()["error"]["details"]
    # one problem, the real one: no "found 0 outlines" after an outline that failed
    assert len(details) == 1, details
    assert details[0]["index"] == index
    for phrase in says:
        assert phrase in details[0]["reason"]
    assert _state(client, site_id, admin) == before
