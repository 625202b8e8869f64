"""What a validated batch hands to the workers: its samples by kind, unset fields left out."""

from __future__ import annotations

from app.ingest.schemas import IngestBatch
from app.ingest.service import batch_samples

T0 = 1_700_000_000_000


def test_a_batch_is_handed_over_by_kind_without_empty_kinds_or_unset_fields() -> None:
    batch = IngestBatch.model_validate(
        {
            "device_id": "d",
            "site_id": "s",
            "wifi": [
                {"t": T0, "id": "aa:00:00:00:00:01", "rssi": -60, "last_seen": T0 - 900},
                {"t": T0, "id": "aa:00:00:00:00:02", "rssi": -71.5},
            ],
            "imu": [{"t": T0 + 20, "acc": [0, 0, 9.8]}],
        }
    )
    assert batch_samples(batch) == {
        "wifi": [
            {"t": T0, "id": "aa:00:00:00:00:01", "rssi": -60.0, "last_seen": T0 - 900},
            {"t": T0, "id": "aa:00:00:00:00:02", "rssi": -71.5},
        ],
        "imu": [{"t": T0 + 20, "acc": [0.0, 0.0, 9.8]}],
    }
