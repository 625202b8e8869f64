"""A batch's samples reach the engine as the site's table rows, sorted by time within each kind,
fields kept together, with what the site cannot use counted."""

from __future__ import annotations

import numpy as np

from app.engine.samples import RssiReadings
from app.sites.assembly import LoadedSite
from app.workers.convert import _sorted, to_batch

BEACON = "FDA50693-A4E2-4FB1-AFCF-C6EB07647825_1_{}"


def _readings(t: list[int]) -> RssiReadings:
    return RssiReadings(
        np.array(t, np.int64), np.arange(len(t), dtype=np.int32), -50.0 - np.arange(len(t))
    )


def test_readings_out_of_order_are_sorted_with_their_fields_and_ties_kept_in_order() -> None:
    out = _sorted(_readings([30, 10, 20, 10]))
    assert out.t.tolist() == [10, 10, 20, 30]
    assert out.tx.tolist() == [1, 3, 2, 0]
    assert out.rssi.tolist() == [-51.0, -53.0, -52.0, -50.0]


def test_readings_in_order_and_empty_ones_are_passed_through() -> None:
    ordered = _readings([10, 10, 20])
    assert _sorted(ordered) is ordered
    empty = _readings([])
    assert _sorted(empty) is empty


def test_every_kind_becomes_the_sites_rows_and_unknown_ids_are_counted(
    office: LoadedSite,
) -> None:
    old = office.tuning.wifi_max_age_ms + 1
    batch, skipped = to_batch(
        office,
        {
            "ble": [
                {"t": 2000, "id": BEACON.format(2).lower(), "rssi": -70.0},
                {"t": 1000, "id": BEACON.format(1), "rssi": -60.0},
                {"t": 1000, "id": "not-a-beacon", "rssi": -80.0},
            ],
            "wifi": [{"t": 50_000, "last_seen": 50_000 - old, "id": "aa:bb", "rssi": -50.0}],
            "uwb": [
                {"t": 1500, "anchor": "A2", "range": 3.5},
                {"t": 1000, "anchor": "A1", "range": 2.0, "std": 0.1},
                {"t": 1000, "anchor": "Z9", "range": 1.0},
            ],
            "uwb_fix": [
                {"t": 1000, "x": 1.0, "y": 2.0, "floor_id": "F1"},
                {"t": 1100, "x": 3.0, "y": 4.0, "z": 1.5},
                {"t": 1200, "x": 5.0, "y": 6.0, "floor_id": "F9"},
            ],
            "baro": [{"t": 1000, "hpa": 1010.5}],
        },
    )
    beacon = office.transmitter_index
    assert batch.rssi.t.tolist() == [1000, 2000]
    assert batch.rssi.tx.tolist() == [
        beacon[BEACON.format(1).lower()],
        beacon[BEACON.format(2).lower()],
    ]
    assert batch.rssi.rssi.tolist() == [-60.0, -70.0]
    assert batch.ranges.anchor.tolist() == [office.anchor_index["A1"], office.anchor_index["A2"]]
    assert batch.ranges.range.tolist() == [2.0, 3.5]
    assert batch.ranges.std[0] == 0.1 and np.isnan(batch.ranges.std[1])
    assert batch.fixes.xyz.tolist() == [[1.0, 2.0, 0.0], [3.0, 4.0, 1.5]]
    assert batch.fixes.floor.tolist() == [office.floor_index["F1"], 0]
    assert batch.pressure.hpa.tolist() == [1010.5]
    assert len(batch.imu) == 0 and len(batch.sightings) == 0
    # the unknown beacon, anchor and floor; the WiFi reading heard too long before its scan
    assert (skipped.unknown_ids, skipped.stale) == (3, 1)
