"""A shard: messages routed to their devices, silence on its clock, and drain at hand-over."""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.core.config import Settings
from app.core.db import session_scope
from app.positions.models import PositionRecord
from app.sites.assembly import LoadedSite
from app.workers import snapshots
from app.workers.device import DeviceSession, public
from app.workers.messages import Done, Emitted, Ingest, decode_results, encode
from app.workers.shard import Shard
from app.workers.snapshot_store import DatabaseSnapshots
from app.workers.trackers import PF, SiteEngines
from tests.workers.conftest import SITE_ID
from tests.workers.office import T0, Clock, Sample, ble_scans, per_second, uwb_ranges

OTHER_ROUTE = np.array([(35.0, 10.0), (15.0, 10.0), (15.0, 16.0)])
"""Along the corridor the other way, then up into a room."""


@pytest.fixture
def settings(office_url: str, tmp_path: Path) -> Settings:
    return Settings(database_url=office_url, home=tmp_path, flush_after_s=2.5, idle_evict_s=60)


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def shard(settings: Settings, office_sessions: sessionmaker[Session], clock: Clock) -> Shard:
    return Shard(shard=0, settings=settings, sessions=office_sessions, clock=clock)


def _id(name: str) -> str:
    """Return a device id of its own for this test (the database is shared)."""
    return f"{name}-{uuid.uuid4().hex[:8]}"


def _message(office: LoadedSite, device_id: str, kind: str, samples: list[Sample]) -> Ingest:
    return Ingest(uuid.uuid4().hex, SITE_ID, device_id, office.version, {kind: samples})


def _positions(results: Sequence[Done | Emitted], device_id: str) -> list[dict[str, Any]]:
    return [
        {k: v for k, v in p.items() if k != "computed_at"}
        for r in results
        if r.device_id == device_id
        for p in r.positions
    ]


def _alone(engines: SiteEngines, device_id: str, kind: str, uploads: list[list[Sample]]) -> list:
    """Return the positions of a device session fed ``uploads`` with no shard around it."""
    session = DeviceSession(device_id=device_id, engines=engines, now=T0)
    out = []
    for samples in uploads:
        session.add({kind: samples}, now=T0)
        batch, _ = session.take(reorder_ms=2000, flush=False)
        if batch is not None:
            assert session.tracker is not None
            out += session.emit(session.tracker.process(batch), now=T0)[0]
    # as a shard answers: without what only the history keeps
    return [{k: v for k, v in public(p).items() if k != "computed_at"} for p in out]


def _two_phones(
    shard: Shard, office: LoadedSite, seconds: int, clock: Clock | None = None
) -> tuple[str, str, list[list[Sample]], list[list[Sample]], list[Done | Emitted]]:
    """Send two phones' BLE scans, one message each a second (the clock advanced when given);
    return their ids, uploads and the shard's results."""
    walker, other = _id("walker"), _id("other")
    mine = per_second(ble_scans(seconds))
    theirs = per_second(ble_scans(seconds, OTHER_ROUTE, seed=2))
    results: list[Done | Emitted] = []
    for a, b in zip(mine, theirs, strict=True):
        results += shard.handle(
            [_message(office, walker, "ble", a), _message(office, other, "ble", b)]
        )
        if clock is not None:
            clock.advance(1.0)
    return walker, other, mine, theirs, results


def test_interleaved_messages_reach_their_own_devices(
    shard: Shard, office: LoadedSite, engines: SiteEngines
) -> None:
    walker, other = _id("walker"), _id("other")
    mine = per_second(uwb_ranges(10))
    theirs = per_second(uwb_ranges(10, OTHER_ROUTE))
    results = []
    for a, b in zip(mine, theirs, strict=True):
        results += shard.handle(
            [_message(office, walker, "uwb", a), _message(office, other, "uwb", b)]
        )

    assert set(shard.devices) == {(SITE_ID, walker), (SITE_ID, other)}
    assert [r.device_id for r in results] == [walker, other] * 10
    assert _positions(results, walker) == _alone(engines, walker, "uwb", mine)
    assert _positions(results, other) == _alone(engines, other, "uwb", theirs)


def test_devices_sharing_the_particle_filter_get_the_positions_each_would_get_alone(
    shard: Shard, office: LoadedSite
) -> None:
    walker, other, mine, theirs, results = _two_phones(shard, office, 12)

    kinds = {d.tracker.kind for d in shard.devices.values() if d.tracker is not None}
    assert kinds == {PF}
    # each alone: in a particle-filter engine of its own
    for device_id, uploads in ((walker, mine), (other, theirs)):
        alone = _alone(SiteEngines.for_site(office), device_id, "ble", uploads)
        assert len(alone) >= 9
        assert _positions(results, device_id) == alone


def test_silence_on_the_shard_clock_flushes_a_device_then_evicts_it(
    shard: Shard, office: LoadedSite, clock: Clock, office_sessions: sessionmaker[Session]
) -> None:
    phone = _id("phone")
    results = []
    for samples in per_second(ble_scans(8)):
        results += shard.handle([_message(office, phone, "ble", samples)])
        clock.advance(1.0)
    handled = _positions(results, phone)
    device = shard.devices[(SITE_ID, phone)]
    assert device.buffer, "the newest samples wait in the reorder window"

    clock.advance(2.4 - 1.0)  # 2.4 s after the last upload
    assert shard.tick() == []
    assert device.buffer

    clock.advance(0.1)  # silent for flush_after_s
    flushed = _positions(shard.tick(), phone)
    assert not device.buffer and not device.pending
    # one position per scan: those of the buffered scans, and the last scan's window,
    # still open in the filter, through the filter's flush
    assert [p["t"] for p in handled] == [T0 + 1000 * k + 90 for k in range(5)]
    assert [p["t"] for p in flushed] == [T0 + 1000 * k + 90 for k in (5, 6, 7)]

    pf = shard.sites.engines[SITE_ID].pf
    assert phone in pf.devices
    clock.advance(60)  # silent for idle_evict_s
    assert shard.tick() == []
    assert (SITE_ID, phone) not in shard.devices
    assert phone not in pf.devices, "closing the device freed its slot in the shared engine"
    with session_scope(office_sessions) as db:
        stored = DatabaseSnapshots().load(db, (SITE_ID, phone))
    assert stored is not None, "evicting stored the device's snapshot under its site"


def test_devices_gone_quiet_together_are_flushed_in_one_call_of_their_shared_engine(
    shard: Shard, office: LoadedSite, clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    walker, other, mine, theirs, results = _two_phones(shard, office, 8, clock)
    pf = shard.sites.engines[SITE_ID].pf
    calls: list[list[str]] = []
    flush = pf.flush

    def counted(device_ids: list[str]) -> Any:
        calls.append(list(device_ids))
        return flush(device_ids)

    monkeypatch.setattr(pf, "flush", counted)
    clock.advance(1.5)  # both silent for flush_after_s
    results += shard.tick()

    assert calls == [[walker, other]]
    assert not any(d.pending for d in shard.devices.values())
    # each device's positions, the flushed last window included, as it would get alone
    for device_id, uploads in ((walker, mine), (other, theirs)):
        alone = SiteEngines.for_site(office)
        session = DeviceSession(device_id=device_id, engines=alone, now=T0)
        expected = []
        for k, samples in enumerate(uploads):
            session.add({"ble": samples}, now=T0)
            batch, _ = session.take(reorder_ms=2000, flush=k == len(uploads) - 1)
            if batch is not None:
                assert session.tracker is not None
                expected += session.emit(session.tracker.process(batch), now=T0)[0]
        expected += session.emit(session.flush_filter(), now=T0)[0]
        flushed = [{k: v for k, v in public(p).items() if k != "computed_at"} for p in expected]
        assert [p["t"] for p in flushed][-3:] == [T0 + 1000 * k + 90 for k in (5, 6, 7)]
        assert _positions(results, device_id) == flushed


def test_a_silent_device_is_flushed_while_one_heard_before_it_keeps_uploading(
    shard: Shard, office: LoadedSite, clock: Clock
) -> None:
    early, late = _id("early"), _id("late")
    mine = per_second(ble_scans(6))
    theirs = per_second(ble_scans(6, OTHER_ROUTE, seed=2))
    for k in range(6):
        # ``early`` uploads every second; ``late`` joins a second later, leaves at 3 s
        messages = [_message(office, early, "ble", mine[k])]
        if 1 <= k <= 3:
            messages.append(_message(office, late, "ble", theirs[k]))
        shard.handle(messages)
        clock.advance(1.0)

    results = shard.tick()  # late silent for 3 s, early for 1 s

    assert _positions(results, late) and not _positions(results, early)
    assert not shard.devices[(SITE_ID, late)].pending
    assert shard.devices[(SITE_ID, early)].pending


def test_a_device_uploading_slower_than_the_flush_time_is_flushed_after_its_own_periods(
    shard: Shard, office: LoadedSite, clock: Clock
) -> None:
    tag = _id("tag")
    scans = per_second(ble_scans(4))
    for samples in scans:
        shard.handle([_message(office, tag, "ble", samples)])
        clock.advance(4.0)  # one upload every 4 s
    device = shard.devices[(SITE_ID, tag)]
    assert device.period_ms == pytest.approx(4000.0)
    assert device.pending
    # 4 s after its last upload, past flush_after_s: its next batch is still due
    assert shard.tick() == [] and device.pending
    clock.advance(6.0 - 0.1)  # just short of 2.5 periods (10 s)
    assert shard.tick() == [] and device.pending
    clock.advance(0.1)
    assert _positions(shard.tick(), tag)
    assert not device.pending
    # a pause of a minute moves the period by one gap of at most four periods
    clock.advance(50.0)
    shard.handle([_message(office, tag, "ble", per_second(ble_scans(6))[5])])
    assert device.period_ms == pytest.approx(4000.0 + 0.25 * (16000.0 - 4000.0))


def test_drain_positions_what_is_buffered_snapshots_every_device_and_lets_them_go(
    shard: Shard, office: LoadedSite, office_sessions: sessionmaker[Session]
) -> None:
    tag, phone = _id("tag"), _id("phone")
    ranges, scans = uwb_ranges(6), ble_scans(6)
    for a, b in zip(per_second(ranges), per_second(scans), strict=True):
        shard.handle([_message(office, tag, "uwb", a), _message(office, phone, "ble", b)])
    assert all(d.buffer for d in shard.devices.values())

    drained = shard.drain()

    assert _positions(drained, tag) and _positions(drained, phone)
    assert shard.devices == {}
    assert phone not in shard.sites.engines[SITE_ID].pf.devices
    with session_scope(office_sessions) as db:
        for device_id, last in ((tag, ranges[-1]["t"]), (phone, scans[-1]["t"])):
            stored = DatabaseSnapshots().load(db, (SITE_ID, device_id))
            assert stored is not None
            state = snapshots.decode(stored)
            assert state["processed_t"] == last
            assert msgspec.msgpack.decode(state["buffer"]) == [] and not state["unflushed"]


def test_the_next_shard_resumes_a_drained_device_from_its_snapshot(
    settings: Settings,
    office_sessions: sessionmaker[Session],
    office: LoadedSite,
    clock: Clock,
) -> None:
    tag = _id("tag")
    uploads = per_second(uwb_ranges(12))
    first = Shard(shard=0, settings=settings, sessions=office_sessions, clock=clock)
    results: list[Done | Emitted] = []
    for samples in uploads[:6]:
        results += first.handle([_message(office, tag, "uwb", samples)])
    results += first.drain()

    second = Shard(shard=0, settings=settings, sessions=office_sessions, clock=clock)
    # the last upload is delivered again (at least once), then the walk goes on
    for samples in uploads[5:]:
        results += second.handle([_message(office, tag, "uwb", samples)])

    assert second.counters["restored"] == 1
    assert second.counters["late"] == len(uploads[5])
    ts = [p["t"] for p in _positions(results, tag)]
    assert ts == sorted(set(ts)), "no position is emitted twice"
    assert ts[-1] >= uploads[-1][0]["t"] - 2000


def test_a_batch_positioned_by_two_owners_is_stored_once(
    settings: Settings,
    office_sessions: sessionmaker[Session],
    office: LoadedSite,
    clock: Clock,
) -> None:
    """A worker that stalled past its lease and the one that took its shard both run the
    same uploads, neither seeing the other's positions first: the history keeps one."""
    tag = _id("tag")
    uploads = per_second(uwb_ranges(8))
    stale = Shard(shard=0, settings=settings, sessions=office_sessions, clock=clock)
    owner = Shard(shard=0, settings=settings, sessions=office_sessions, clock=clock)
    answered: list[Done | Emitted] = []
    for samples in uploads:
        for shard in (stale, owner):
            answered += shard.handle([_message(office, tag, "uwb", samples)])

    emitted = [p["t"] for p in _positions(answered, tag)]
    assert len(emitted) > len(set(emitted)), "both owners positioned the uploads"
    with session_scope(office_sessions) as db:
        stored = db.scalars(
            select(PositionRecord.t).where(
                PositionRecord.site_id == SITE_ID, PositionRecord.device_id == tag
            )
        ).all()
    assert sorted(stored) == sorted(set(emitted))


def test_what_a_shard_answers_is_plain_data_the_brokers_carry_unchanged(
    shard: Shard, office: LoadedSite
) -> None:
    tag, phone = _id("tag"), _id("phone")
    results: list[Done | Emitted] = []
    # the tag walks into the Lab (zone events); the phone is on the particle filter
    for a, b in zip(per_second(uwb_ranges(27)), per_second(ble_scans(27)), strict=True):
        results += shard.handle(
            [_message(office, tag, "uwb", a), _message(office, phone, "ble", b)]
        )
    results += shard.drain()

    assert (
        any(r.events for r in results) and _positions(results, tag) and _positions(results, phone)
    )
    assert decode_results(encode(results)) == results
    assert decode_results(encode([shard.stats()])) == [shard.stats()]


def test_devices_started_together_spread_their_periodic_snapshots_over_the_period(
    shard: Shard, office: LoadedSite, settings: Settings, clock: Clock
) -> None:
    # fixed ids, fixed phases: 1 to 5 a round after the first
    tags = [f"spread-tag{i}" for i in range(30)]
    uploads = per_second(uwb_ranges(25))
    stored_per_round = []
    stored_at: dict[str, list[int]] = {tag: [] for tag in tags}
    for samples in uploads:
        before = shard.counters["snapshots"]
        shard.handle([_message(office, tag, "uwb", samples) for tag in tags])
        clock.advance(1.0)
        stored_per_round.append(shard.counters["snapshots"] - before)
        for device in shard.devices.values():
            times = stored_at[device.device_id]
            if device.snapshot_t >= 0 and device.snapshot_t not in times:
                times.append(device.snapshot_t)

    period = settings.snapshot_every_ms
    first = next(i for i, n in enumerate(stored_per_round) if n)
    assert stored_per_round[first] == len(tags), "a device is stored once it has a state"
    # 3 a round on average; all 30 in one round every 10 s without the phases
    assert max(stored_per_round[first + 1 :]) <= 10
    for times in stored_at.values():
        gaps = np.diff(times)
        assert len(times) >= 3, "two periodic snapshots in 24 s of a 10 s period"
        assert gaps[1:].min() >= period - 1000 and gaps.max() <= period
