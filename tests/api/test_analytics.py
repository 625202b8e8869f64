"""Analytics on stored history: a scripted walk with known times in and out of the Lab zone
(stored through the services the workers use), and a walk through the real ingest."""

from __future__ import annotations

import csv
import io
import json

from fastapi.testclient import TestClient

from app.analytics.service import store_zone_events
from app.devices.service import touch_devices
from app.positions.service import store as store_positions
from app.state import app_state

T0 = 1_700_000_000_000
S = 1000


def _position(site: str, device: str, t: int, x: float, y: float) -> dict:
    return {
        "site_id": site,
        "device_id": device,
        "floor_id": "G",
        "t": t,
        "x": x,
        "y": y,
        "z": 0.0,
        "heading": None,
        "accuracy": 1.0,
        "speed": None,
        "method": "ekf",
        "computed_at": t,
        "smoothed": False,
    }


def _event(site: str, device: str, event: str, t: int) -> dict:
    return {
        "type": "zone",
        "site_id": site,
        "zone": "Lab",
        "device_id": device,
        "floor_id": "G",
        "event": event,
        "t": t,
    }


def _walk(client: TestClient, site: str) -> None:
    """Store two devices' walks: a inside the Lab from 10 s to 100 s then out (at 1 Hz,
    0-100 s); b inside from 70 s, still inside at its last position (150 s)."""
    rows = [
        _position(site, "a", T0 + k * S, 14.0 if 10 <= k < 100 else 4.0, 4.0) for k in range(101)
    ]
    rows += [_position(site, "b", T0 + k * S, 13.0, 3.0) for k in range(70, 151)]
    events = [
        _event(site, "a", "enter", T0 + 10 * S),
        _event(site, "a", "exit", T0 + 100 * S),
        _event(site, "b", "enter", T0 + 70 * S),
    ]
    with app_state(client).sessions() as db:
        store_positions(db, rows)
        store_zone_events(db, events)
        # a batch positioned twice stores its events once
        store_zone_events(db, events)
        db.commit()


def test_occupancy_counts_entries_devices_and_dwell_to_the_second(
    client: TestClient, admin: dict, site_id: str
) -> None:
    _walk(client, site_id)
    r = client.get(
        f"/v1/sites/{site_id}/zones/Lab/occupancy?from={T0}&to={T0 + 180 * S}&bucket_s=60",
        headers=admin,
    )
    assert r.status_code == 200, r.text
    got = [(b["t"], b["devices"], b["entries"], b["dwell_s"]) for b in r.json()["buckets"]]
    assert got == [
        # a: 10-60 s
        (T0, 1, 1, 50.0),
        # a across the boundary at 60 s (60-100 s), b from 70 s: both counted, dwell split
        (T0 + 60 * S, 2, 1, 40.0 + 50.0),
        # b up to its last position at 150 s, not to 'to'
        (T0 + 120 * S, 1, 0, 30.0),
    ]
    # a range starting while both are inside counts them without an entry
    r = client.get(
        f"/v1/sites/{site_id}/zones/Lab/occupancy?from={T0 + 80 * S}&to={T0 + 140 * S}&bucket_s=60",
        headers=admin,
    )
    assert [(b["devices"], b["entries"], b["dwell_s"]) for b in r.json()["buckets"]] == [
        (2, 0, 20.0 + 60.0)
    ]


def test_heatmap_total_is_the_walks_duration_plus_the_cap(
    client: TestClient, admin: dict, site_id: str, settings
) -> None:
    _walk(client, site_id)
    r = client.get(
        f"/v1/sites/{site_id}/floors/G/heatmap?from={T0}&to={T0 + 3600 * S}&cell=1",
        headers=admin,
    )
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["origin"] == [0.0, 0.0] and body["shape"] == [10, 20] and body["cell"] == 1.0
    seconds = body["seconds"]
    total = sum(v for row in seconds for v in row if v is not None)
    cap = settings.heatmap_gap_cap_s
    # a: 0-100 s, b: 70-150 s at 1 Hz, each last position weighed by the cap
    assert total == 100 + 80 + 2 * cap
    # a's 90 s inside the Lab at (14, 4), b's 80 s + cap at (13, 3); row 0 at y0
    assert seconds[4][14] == 90.0
    assert seconds[3][13] == 80.0 + cap
    assert seconds[4][4] == 10.0 + cap
    png = client.get(
        f"/v1/sites/{site_id}/floors/G/heatmap?from={T0}&to={T0 + 3600 * S}",
        headers=admin | {"Accept": "image/png"},
    )
    assert png.headers["content-type"] == "image/png" and png.content[:4] == b"\x89PNG"


def test_csv_and_geojson_exports_have_a_row_per_stored_position(
    client: TestClient, admin: dict, site_id: str, settings
) -> None:
    _walk(client, site_id)
    with app_state(client).sessions() as db:
        # a device must exist for its history to be read
        touch_devices(db=db, heard=[((site_id, "a"), T0 + 100 * S)], now=T0)
        db.commit()
    r = client.get(
        f"/v1/sites/{site_id}/devices/a/positions", headers=admin | {"Accept": "text/csv"}
    )
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(r.text)))
    assert [int(row["t"]) for row in rows] == [T0 + k * S for k in range(101)]
    r = client.get(
        f"/v1/sites/{site_id}/devices/a/positions?format=geojson&from={T0 + 10 * S}"
        f"&to={T0 + 19 * S}",
        headers=admin,
    )
    features = json.loads(r.text)["features"]
    assert [f["properties"]["t"] for f in features] == [T0 + k * S for k in range(10, 20)]
    assert features[0]["geometry"]["coordinates"] == [14.0, 4.0, 0.0]
    # the site's export: both devices, every position in the range
    r = client.get(f"/v1/sites/{site_id}/positions?from={T0}&to={T0 + 3600 * S}", headers=admin)
    rows = list(csv.DictReader(io.StringIO(r.text)))
    assert len(rows) == 101 + 81
    assert [int(row["t"]) for row in rows] == sorted(int(row["t"]) for row in rows)
    # JSON stays the default
    assert "items" in client.get(f"/v1/sites/{site_id}/devices/a/positions", headers=admin).json()


def test_limits_are_refused_naming_them(client: TestClient, admin: dict, site_id: str) -> None:
    base = f"/v1/sites/{site_id}"
    month = 40 * 86_400 * S
    cases = [
        (f"{base}/zones/Lab/occupancy?from={T0}&to={T0 + month}", "analytics_max_range_days"),
        (
            f"{base}/zones/Lab/occupancy?from={T0}&to={T0 + 8 * 86_400 * S}&bucket_s=60",
            "analytics_max_buckets",
        ),
        (f"{base}/floors/G/heatmap?from={T0}&to={T0 + month}", "analytics_max_range_days"),
        (f"{base}/zones/Lab/occupancy?from={T0}&to={T0}", "'to'"),
        (f"{base}/zones/Lab/occupancy?from={T0}&to={T0 + S}&bucket_s=30", "bucket_s"),
    ]
    for url, named in cases:
        r = client.get(url, headers=admin)
        assert r.status_code == 422, (url, r.text)
        assert named in json.dumps(r.json()["error"]), (url, r.text)
    r = client.get(f"{base}/zones/Nowhere/occupancy?from={T0}&to={T0 + S}", headers=admin)
    assert r.status_code == 404 and "Nowhere" in r.json()["error"]["message"]


def test_the_ingest_stores_the_zone_events_occupancy_counts(
    client: TestClient, admin: dict, site_id: str
) -> None:
    device = f"{site_id}-walker"
    # east at 1.25 m/s along y = 4 through the Lab (12 ≤ x ≤ 16)
    fixes = [
        {"t": T0 + 200 * k, "x": 10.5 + 0.25 * k, "y": 4.0, "floor_id": "G", "std": 0.1}
        for k in range(38)
    ]
    r = client.post(
        "/v1/ingest?wait=true",
        json={"device_id": device, "site_id": site_id, "uwb_fix": fixes},
        headers=admin,
    )
    assert r.status_code == 200, r.text
    positions = r.json()["positions"]
    # the events are reported at the crossings: the first position inside, the first beyond
    enter = next(p["t"] for p in positions if 12 <= p["x"] <= 16)
    leave = next(p["t"] for p in positions if p["x"] > 16)
    r = client.get(
        f"/v1/sites/{site_id}/zones/Lab/occupancy?from={T0}&to={T0 + 600 * S}&bucket_s=600",
        headers=admin,
    )
    [bucket] = r.json()["buckets"]
    assert (bucket["devices"], bucket["entries"]) == (1, 1)
    assert bucket["dwell_s"] == (leave - enter) / 1000
    # the scripted walk spends 3.2 s in the zone (4 m at 1.25 m/s): to the fix period
    assert abs(bucket["dwell_s"] - 3.2) <= 0.4
