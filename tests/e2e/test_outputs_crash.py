"""Outputs through a crash: a real ``locus serve`` with a webhook output (a receiver in this
test) and an MQTT output (the machine's Mosquitto; skipped, saying so, where none answers on
127.0.0.1:1883) is killed with SIGKILL mid-stream while the receiver refuses, so stored
messages wait in the outbox; restarted on the same database, it delivers every stored
position and zone event to both, signed, under the same webhook-id as before the crash."""

from __future__ import annotations

import signal
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from app.analytics.models import ZoneEventRecord
from app.core.db import make_engine
from app.positions.models import PositionRecord
from tests.conftest import ADMIN_KEY, LiveServer, floor_doc, migrated
from tests.receivers import (
    SECRET,
    Receiver,
    Request,
    Subscriber,
    broker_answers,
    until,
    valid_signature,
)

pytestmark = pytest.mark.skipif(
    not broker_answers(), reason="no MQTT broker answers on 127.0.0.1:1883"
)
ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
SITE = "crash"
T0 = 1_700_000_000_000
DEVICES = ["tag-a", "tag-b", "tag-c"]
ENV = {"LOCUS_OUTPUT_REFRESH_S": "0.5", "LOCUS_OUTPUT_RETRY_MAX_S": "1"}


LAP = [(11.0, 4.0), (18.0, 4.0), (18.0, 8.0), (11.0, 8.0), (11.0, 4.0)]
"""A tag's loop: east through the Lab zone (12 <= x <= 16, 2 <= y <= 6), back outside it."""


def fix(k: int) -> dict[str, Any]:
    """The k-th UWB fix of a tag walking ``LAP`` over and over, 0.25 m every 200 ms."""
    s = 0.25 * (k % 88)
    for (x0, y0), (x1, y1) in zip(LAP, LAP[1:], strict=False):
        leg = abs(x1 - x0) + abs(y1 - y0)
        if s <= leg:
            f = s / leg
            return {"t": T0 + 200 * k, "x": x0 + f * (x1 - x0), "y": y0 + f * (y1 - y0),
                    "floor_id": "G", "std": 0.1}  # fmt: skip
        s -= leg
    raise AssertionError("past the lap")


class Stream:
    """One thread per device posting two fixes a batch (``?wait=true``) until the server
    stops answering; counts the batches answered."""

    def __init__(self, url: str, start: int) -> None:
        self.answered = dict.fromkeys(DEVICES, 0)
        self.threads = [
            threading.Thread(target=self._run, args=(url, d, start), daemon=True) for d in DEVICES
        ]
        for thread in self.threads:
            thread.start()

    def _run(self, url: str, device: str, start: int) -> None:
        with httpx.Client(base_url=url, headers=ADMIN, timeout=30) as http:
            for k in range(start, start + 10_000, 2):
                body = {"device_id": device, "site_id": SITE, "uwb_fix": [fix(k), fix(k + 1)]}
                try:
                    r = http.post("/v1/ingest?wait=true", json=body)
                except httpx.HTTPError:
                    return
                assert r.status_code == 200, r.text
                self.answered[device] += 1

    def join(self) -> None:
        """Wait for every device's thread to end."""
        for thread in self.threads:
            thread.join(30)
            assert not thread.is_alive()


def children(pid: int) -> list[int]:
    """Return the pids of ``pid``'s child processes (its workers)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


def alive(pid: int) -> bool:
    """Return whether the process runs (a zombie does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def stored(database_url: str) -> tuple[set[tuple[str, int]], set[tuple[str, str, str, int]]]:
    """Return the stored live positions (device, t) and zone events (device, zone, event,
    t) of the streamed devices, read from the database."""
    engine = make_engine(database_url)
    try:
        with engine.connect() as conn:
            positions = conn.execute(
                select(PositionRecord.device_id, PositionRecord.t).where(
                    PositionRecord.site_id == SITE,
                    PositionRecord.device_id.in_(DEVICES),
                    PositionRecord.smoothed.is_(False),
                )
            )
            events = conn.execute(
                select(
                    ZoneEventRecord.device_id,
                    ZoneEventRecord.zone,
                    ZoneEventRecord.event,
                    ZoneEventRecord.t,
                ).where(ZoneEventRecord.site_id == SITE)
            )
            return {(d, t) for d, t in positions}, {(d, z, e, t) for d, z, e, t in events}
    finally:
        engine.dispose()


def keys(messages: list[dict[str, Any]]) -> tuple[set[tuple[str, int]], set[tuple[Any, ...]]]:
    """Return the positions and zone events among delivered messages, keyed as ``stored``."""
    positions = {(m["device_id"], m["t"]) for m in messages if m["type"] == "position"}
    events = {
        (m["device_id"], m["zone"], m["event"], m["t"]) for m in messages if m["type"] == "zone"
    }
    return positions, events


def in_order(messages: list[dict[str, Any]]) -> bool:
    """Return whether each device's positions first arrived in time order (a redelivery
    after the crash may repeat some: at least once)."""
    seen: dict[str, list[int]] = {}
    for m in messages:
        if m["type"] == "position" and m["t"] not in seen.setdefault(m["device_id"], []):
            seen[m["device_id"]].append(m["t"])
    return all(ts == sorted(ts) for ts in seen.values())


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    server = Receiver()
    yield server
    server.close()


def test_a_crash_with_a_refused_outbox_loses_nothing_after_the_restart(
    new_database: Callable[[], str], tmp_path: Path, receiver: Receiver
) -> None:
    database_url = migrated(new_database())
    prefix = f"crash{uuid.uuid4().hex[:8]}"
    sub = Subscriber(f"{prefix}/#")
    server = LiveServer(database_url=database_url, home=tmp_path, workers=1, env=ENV)
    restarted: LiveServer | None = None
    try:
        http = httpx.Client(base_url=server.url, headers=ADMIN, timeout=30)
        assert http.put(f"/v1/sites/{SITE}", json={"name": SITE}).is_success
        assert http.put(f"/v1/sites/{SITE}/floors/G", json=floor_doc()).is_success
        hook = {"kind": "webhook", "url": receiver.url, "secret": SECRET}
        hook["events"] = ["position", "zone"]  # type: ignore[assignment]
        mq = {"kind": "mqtt", "url": "mqtt://127.0.0.1:1883", "topic_prefix": prefix}
        assert http.put(f"/v1/sites/{SITE}/outputs/hook", json=hook).status_code == 201
        assert http.put(f"/v1/sites/{SITE}/outputs/mq", json=mq).status_code == 201

        # until both outputs deliver, a probe device posts (it is left out of the counts)
        probe = f"{prefix}/{SITE}/devices/probe/position"
        sent = [0]

        def delivering() -> bool:
            body = {"device_id": "probe", "site_id": SITE, "uwb_fix": [fix(sent[0])]}
            sent[0] += 1
            assert http.post("/v1/ingest?wait=true", json=body).status_code == 200
            return bool(receiver.accepted()) and bool(sub.on(probe))

        until(delivering, 60, "both outputs delivering")

        # the receiver refuses; devices stream; once stored messages wait, SIGKILL
        receiver.refusing = True
        stream = Stream(server.url, 0)
        exits = f"{prefix}/{SITE}/zones/Lab/events"
        until(
            lambda: (
                min(stream.answered.values()) >= 30
                and http.get(f"/v1/sites/{SITE}/outputs/hook").json()["status"]["pending"] > 150
                and sum(r.status == 503 for r in receiver.requests) >= 2
                and len([m for m in sub.on(exits) if m["event"] == "exit"]) >= 3
            ),
            90,
            "a refused backlog mid-stream",
        )
        workers = children(server.process.pid)
        server.process.send_signal(signal.SIGKILL)
        server.process.wait(30)
        killed_at = len(receiver.requests)
        stream.join()
        # its workers see their pipes close and exit: no writer from the old run stays
        until(lambda: not any(alive(pid) for pid in workers), 30, "the workers' exit")
        http.close()
        positions, events = stored(database_url)
        assert len(events) >= 6 and len(positions) > 150

        # the same database; the receiver refuses two more attempts, then accepts
        receiver.refusals = 2
        receiver.refusing = False
        restarted = LiveServer(database_url=database_url, home=tmp_path, workers=1, env=ENV)
        http = httpx.Client(base_url=restarted.url, headers=ADMIN, timeout=30)
        position_topic = {(d, f"{prefix}/{SITE}/devices/{d}/position") for d in DEVICES}

        def everything_delivered() -> bool:
            hooked = keys([m for m in receiver.accepted() if m["device_id"] != "probe"])
            published = {(d, m["t"]) for d, topic in position_topic for m in sub.on(topic)}
            zone_events = {
                (m["device_id"], m["zone"], m["event"], m["t"])
                for p in list(sub.received)
                if p.topic.startswith(f"{prefix}/{SITE}/zones/")
                for m in [p.payload]
            }
            return (
                positions <= hooked[0]
                and events <= hooked[1]
                and positions <= published
                and events <= zone_events
            )

        until(everything_delivered, 120, "every stored position and zone event delivered")
        for output in ("hook", "mq"):
            status = until(
                lambda o=output: (
                    (s := http.get(f"/v1/sites/{SITE}/outputs/{o}").json())["status"]["pending"]
                    == 0
                    and s["status"]
                ),
                30,
                f"output {output} drained",
            )
            assert status["failed"] == 0 and status["last_error"] is None, status
        metrics = http.get("/metrics").text
    finally:
        sub.close()
        if restarted is not None:
            restarted.stop()
        if server.process.poll() is None:
            server.stop()

    # nothing delivered that was not stored, each device's positions in order
    hooked = [m for m in receiver.accepted() if m["device_id"] != "probe"]
    assert keys(hooked)[0] == positions and in_order(hooked)
    published = [p.payload for p in sub.received if p.topic.endswith("/position")]
    assert in_order([m for m in published if m["device_id"] != "probe"])
    # every attempt is signed; an id always carries the same body
    assert all(valid_signature(r, SECRET) for r in receiver.requests)
    bodies: dict[str, set[bytes]] = {}
    for r in receiver.requests:
        bodies.setdefault(r.header("webhook-id"), set()).add(r.body)
    assert [k for k, b in bodies.items() if len(b) > 1] == []
    # the batch refused before the crash is the one sent first after it, under its id
    before: list[Request] = [r for r in receiver.requests[:killed_at] if r.status == 503]
    after = receiver.requests[killed_at:]
    assert {r.header("webhook-id") for r in before} == {after[0].header("webhook-id")}
    assert [r.status for r in after[:3]] == [503, 503, 200]
    assert len({r.header("webhook-id") for r in after[:3]}) == 1
    for output in ("hook", "mq"):
        delivered = f'locus_output_delivered_total{{output_id="{output}",site_id="{SITE}"}}'
        assert delivered in metrics
    print(
        f"outputs through a crash: {len(positions)} positions, {len(events)} zone events "
        f"stored; after the restart every one delivered to the webhook and MQTT; "
        f"{len(before)} refused attempts before the kill, {len(after)} POSTs after"
    )
