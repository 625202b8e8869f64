"""A device session: its reorder window, and a snapshot that resumes it exactly."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from app.workers import snapshots
from app.workers.device import SCAN_DELIVERY_MS, DeviceSession
from app.workers.trackers import UWB, SiteEngines
from tests.workers.office import T0, Sample, per_second, uwb_ranges

REORDER_MS = 2000
NOW = T0 + 60_000


def _feed(
    session: DeviceSession, uploads: list[list[Sample]], *, flush_at_end: bool = True
) -> list[dict[str, Any]]:
    """Upload each list in turn, run what the window releases; return positions and events."""
    out: list[dict[str, Any]] = []
    for i, samples in enumerate(uploads):
        session.add({"uwb": samples}, now=NOW)
        flush = flush_at_end and i == len(uploads) - 1
        batch, skipped = session.take(reorder_ms=REORDER_MS, flush=flush)
        assert skipped.unknown_ids == 0
        if batch is not None:
            assert session.tracker is not None
            assert np.all(np.diff(batch.ranges.t) >= 0), "a released batch is in time order"
            positions, events = session.emit(session.tracker.process(batch), now=NOW)
            out += positions + events
    return out


def test_uploads_that_overtake_each_other_within_the_window_are_used_in_time_order(
    engines: SiteEngines,
) -> None:
    uploads = per_second(uwb_ranges(12))
    # every second upload arrives before the one sent a second earlier
    swapped = [u for pair in zip(uploads[1::2], uploads[::2], strict=True) for u in pair]
    in_order = DeviceSession(device_id="tag", engines=engines, now=NOW)
    overtaken = DeviceSession(device_id="tag", engines=engines, now=NOW)

    expected = _feed(in_order, uploads)
    got = _feed(overtaken, swapped)

    assert len(expected) > 50
    assert got == expected
    assert overtaken.tracker is not None and overtaken.tracker.kind == UWB


def test_samples_at_or_before_what_was_released_are_late_and_repeats_are_duplicates(
    engines: SiteEngines,
) -> None:
    session = DeviceSession(device_id="tag", engines=engines, now=NOW)
    uploads = per_second(uwb_ranges(5))
    for samples in uploads[:4]:
        session.add({"uwb": samples}, now=NOW)
    session.take(reorder_ms=REORDER_MS, flush=False)
    released = session.processed_t
    assert released == T0 + 1900  # up to 2 s before the newest sample (3.9 s)

    late = [s for s in uploads[1] if s["t"] <= released]
    repeated = uploads[3][:5]
    fresh = uploads[4]
    counts = session.add({"uwb": late + repeated + fresh}, now=NOW)

    assert counts == (len(fresh), len(late), len(repeated))


def test_a_restored_snapshot_resumes_the_device_exactly(engines: SiteEngines) -> None:
    uploads = per_second(uwb_ranges(27))
    uninterrupted = _feed(DeviceSession(device_id="tag", engines=engines, now=NOW), uploads)

    before = DeviceSession(device_id="tag", engines=engines, now=NOW)
    first = _feed(before, uploads[:24], flush_at_end=False)
    # stored as the shard stores it, mid-walk: inside the Lab, samples waiting in the window
    state = snapshots.decode(snapshots.encode(before.snapshot()))
    assert before.zones.inside == {"Lab"} and before.buffer

    after = DeviceSession(device_id="tag", engines=engines, now=NOW)
    after.restore(state)
    assert after.buffer == before.buffer
    assert after.zones.inside == before.zones.inside
    rest = _feed(after, uploads[24:])

    assert any(m["type"] == "zone" and m["zone"] == "Lab" for m in first)
    assert first + rest == uninterrupted


def test_a_snapshot_with_the_buffer_as_json_text_resumes_the_same_samples(
    engines: SiteEngines,
) -> None:
    # earlier releases stored the reorder buffer as JSON text
    before = DeviceSession(device_id="tag", engines=engines, now=NOW)
    _feed(before, per_second(uwb_ranges(6)), flush_at_end=False)
    state = snapshots.decode(snapshots.encode(before.snapshot()))
    assert before.buffer and isinstance(state["buffer"], bytes)
    state["buffer"] = json.dumps([list(item) for item in before.buffer])

    after = DeviceSession(device_id="tag", engines=engines, now=NOW)
    after.restore(state)

    assert after.buffer == before.buffer
    assert after.seen == before.seen


def test_wifi_heard_before_inertial_samples_already_used_is_not_late(
    engines: SiteEngines,
) -> None:
    # a phone delivers a scan when it completes, its readings timed when each was heard
    session = DeviceSession(device_id="phone", engines=engines, now=NOW)
    imu = [{"t": T0 + 100 * i, "acc": [0.0, 0.0, 9.8]} for i in range(40)]
    scan = [{"t": T0 + 1000 + 10 * i, "id": f"aa:00:00:00:00:0{i}", "rssi": -60} for i in range(3)]
    ranges = per_second(uwb_ranges(4))[0]
    session.add({"imu": imu, "wifi": scan, "uwb": ranges}, now=NOW)
    session.take(reorder_ms=REORDER_MS, flush=True)
    assert session.processed_t == T0 + 3900 and session.processed_wifi_t == T0 + 1020

    next_scan = [{"t": T0 + 2500, "id": "aa:00:00:00:00:01", "rssi": -58}]
    repeat_of_used = [{"t": T0 + 1010, "id": "aa:00:00:00:00:01", "rssi": -61}]
    old_imu = [{"t": T0 + 3000, "acc": [0.0, 0.0, 9.8]}]
    counts = session.add({"wifi": next_scan + repeat_of_used, "imu": old_imu}, now=NOW)
    assert counts == (1, 2, 0)

    # WiFi further behind everything than a scan takes is late all the same
    stale = [{"t": T0 + 3900 - SCAN_DELIVERY_MS, "id": "aa:00:00:00:00:02", "rssi": -70}]
    assert session.add({"wifi": stale}, now=NOW) == (0, 1, 0)


def test_wifi_heard_longer_before_its_scan_than_the_site_uses_is_counted_stale(
    engines: SiteEngines,
) -> None:
    # the site's build chose how old a reading its engines use; older ones are counted
    max_age = engines.site.tuning.wifi_max_age_ms
    beacon = "FDA50693-A4E2-4FB1-AFCF-C6EB07647825_1_{}"
    scan_t = T0 + 10_000
    scan = [
        {"t": scan_t, "id": beacon.format(1), "rssi": -60, "last_seen": scan_t - 500},
        {"t": scan_t, "id": beacon.format(2), "rssi": -65, "last_seen": scan_t - max_age},
        {"t": scan_t, "id": beacon.format(3), "rssi": -70, "last_seen": scan_t - max_age - 1},
    ]
    session = DeviceSession(device_id="phone", engines=engines, now=NOW)
    assert session.add({"wifi": scan}, now=NOW) == (3, 0, 0)
    batch, skipped = session.take(reorder_ms=REORDER_MS, flush=True)
    assert batch is not None
    assert (skipped.stale, skipped.unknown_ids) == (1, 0)
    # the two used are one scan, timed when its freshest reading was heard
    assert batch.rssi.t.tolist() == [scan_t - 500, scan_t - 500]
    assert sorted(batch.rssi.rssi.tolist()) == [-65.0, -60.0]
