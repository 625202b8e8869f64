"""The accuracy map endpoint: JSON grids per docs/api.md, a PNG heatmap on request."""

from __future__ import annotations

import numpy as np
from fastapi.testclient import TestClient


def test_accuracy_json_grids(client: TestClient, admin: dict, site_id: str) -> None:
    r = client.get(
        f"/v1/sites/{site_id}/floors/G/accuracy?tech=ble&z=1.0&cell=1&samples=50", headers=admin
    )
    assert r.status_code == 200, r.text
    body = r.json()
    ny, nx = body["shape"]
    assert body["cell"] == 1.0 and len(body["sigma_x"]) == ny and len(body["sigma_x"][0]) == nx
    sx = np.array(body["sigma_x"], dtype=float)
    # three transmitters on one plane with the receiver at another height: observable in
    # x and y everywhere; more readings shrink the error as 1/sqrt(samples)
    assert np.isfinite(sx).all()
    r4 = client.get(
        f"/v1/sites/{site_id}/floors/G/accuracy?tech=ble&z=1.0&cell=1&samples=200", headers=admin
    )
    assert np.allclose(np.array(r4.json()["sigma_x"], dtype=float), sx / 2, rtol=1e-3)


def test_accuracy_png(client: TestClient, admin: dict, site_id: str) -> None:
    r = client.get(
        f"/v1/sites/{site_id}/floors/G/accuracy", headers=admin | {"Accept": "image/png"}
    )
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert r.content[:8] == b"\x89PNG\r\n\x1a\n"


def test_accuracy_without_anchors_is_unobservable(
    client: TestClient, admin: dict, site_id: str
) -> None:
    body = client.get(
        f"/v1/sites/{site_id}/floors/G/accuracy?tech=uwb&cell=2", headers=admin
    ).json()
    assert all(v is None for row in body["sigma_x"] for v in row)


def test_accuracy_bad_requests(client: TestClient, admin: dict, site_id: str) -> None:
    assert client.get(f"/v1/sites/{site_id}/floors/X/accuracy", headers=admin).status_code == 404
    assert (
        client.get(f"/v1/sites/{site_id}/floors/G/accuracy?tech=lora", headers=admin).status_code
        == 422
    )
    assert (
        client.get(f"/v1/sites/{site_id}/floors/G/accuracy?cell=0", headers=admin).status_code
        == 422
    )
