"""Outputs: validation and secrets, and delivery to a real webhook receiver and the
machine's real Mosquitto (skipped, saying so, where no broker answers on 127.0.0.1:1883):
signatures and retries, Home Assistant discovery, a per-output rate limit, batches for a
slow receiver."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.core.config import Settings
from tests.receivers import SECRET, Receiver, Subscriber, broker_answers, until, valid_signature

T0 = 1_700_000_000_000
needs_broker = pytest.mark.skipif(
    not broker_answers(), reason="no MQTT broker answers on 127.0.0.1:1883"
)


def walk(site_id: str, device: str, t0: int = T0) -> dict[str, Any]:
    """A tag walking east along y = 4 through the Lab zone (12 <= x <= 16) and out."""
    fixes = [
        {"t": t0 + 200 * k, "x": 10.5 + 0.25 * k, "y": 4.0, "floor_id": "G", "std": 0.1}
        for k in range(38)
    ]
    return {"device_id": device, "site_id": site_id, "uwb_fix": fixes}


def after_refresh(settings: Settings) -> None:
    """Wait until the workers have read the site's outputs again: an output gets what is
    stored from at most ``output_refresh_s`` after its creation."""
    time.sleep(settings.output_refresh_s + 0.5)


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    server = Receiver()
    yield server
    server.close()


def test_bad_outputs_get_422_naming_the_fault_and_change_nothing(
    client: TestClient, admin: dict, site_id: str
) -> None:
    url = f"/v1/sites/{site_id}/outputs/o1"
    cases = [
        ({"kind": "webhook", "url": "ftp://x/", "secret": "long-enough"}, "ftp"),
        ({"kind": "mqtt", "url": "http://broker:1883"}, "http"),
        ({"kind": "mqtt", "url": "mqtt://h:1883", "events": ["position", "walk"]}, "walk"),
        ({"kind": "webhook", "url": "https://x/", "secret": "whsec_!!!"}, "base64"),
        ({"kind": "mqtt", "url": "mqtt://u:pw@h:1883"}, "password"),
    ]
    for body, named in cases:
        r = client.put(url, json=body, headers=admin)
        assert r.status_code == 422, r.text
        assert named in r.json()["error"]["message"], r.text
    assert client.get(f"/v1/sites/{site_id}/outputs", headers=admin).json()["items"] == []


def test_secrets_are_never_returned(client: TestClient, admin: dict, site_id: str) -> None:
    body = {"kind": "mqtt", "url": "mqtt://127.0.0.1:9", "username": "u", "password": "pw-xyz"}
    r = client.put(f"/v1/sites/{site_id}/outputs/m", json=body, headers=admin)
    assert r.status_code == 201, r.text
    hook = {"kind": "webhook", "url": "http://127.0.0.1:9/", "secret": "hook-secret-1"}
    assert client.put(f"/v1/sites/{site_id}/outputs/w", json=hook, headers=admin).is_success
    listing = client.get(f"/v1/sites/{site_id}/outputs", headers=admin)
    assert "pw-xyz" not in listing.text and "hook-secret-1" not in listing.text
    assert [o["has_secret"] for o in listing.json()["items"]] == [True, True]
    one = client.get(f"/v1/sites/{site_id}/outputs/w", headers=admin).json()
    assert set(one["status"]) == {"delivered", "pending", "failed", "last_error", "last_ok_at"}
    assert client.delete(f"/v1/sites/{site_id}/outputs/m", headers=admin).status_code == 204
    assert client.get(f"/v1/sites/{site_id}/outputs/m", headers=admin).status_code == 404


def status_of(client: TestClient, admin: dict, site_id: str, output_id: str) -> dict[str, Any]:
    """Return the output's delivery status."""
    r = client.get(f"/v1/sites/{site_id}/outputs/{output_id}", headers=admin)
    assert r.status_code == 200, r.text
    return dict(r.json()["status"])


def drained(client: TestClient, admin: dict, site_id: str, output_id: str) -> dict[str, Any]:
    """Wait until nothing waits for the output; return its status."""
    return until(
        lambda: (s := status_of(client, admin, site_id, output_id))["pending"] == 0 and s,
        what=f"output {output_id} drained",
    )


def stored_positions(client: TestClient, admin: dict, site_id: str, device: str) -> list[int]:
    """Return the times of the device's stored positions, ascending."""
    url = f"/v1/sites/{site_id}/devices/{device}/positions?limit=1000"
    return [p["t"] for p in client.get(url, headers=admin).json()["items"]]


def test_zone_events_reach_a_webhook_signed_and_after_a_refusal(
    client: TestClient, admin: dict, site_id: str, receiver: Receiver, settings: Settings
) -> None:
    body = {"kind": "webhook", "url": receiver.url, "secret": SECRET, "events": ["zone"]}
    assert client.put(f"/v1/sites/{site_id}/outputs/hook", json=body, headers=admin).is_success
    after_refresh(settings)
    receiver.refusals = 2
    r = client.post("/v1/ingest?wait=true", json=walk(site_id, "walker"), headers=admin)
    assert r.status_code == 200, r.text
    got = until(lambda: receiver.accepted() if len(receiver.accepted()) >= 2 else None, 60)
    assert [(m["type"], m["event"], m["zone"]) for m in got] == [
        ("zone", "enter", "Lab"),
        ("zone", "exit", "Lab"),
    ]
    fields = {"x", "y", "floor_id", "accuracy"}
    assert all(m["site_id"] == site_id and fields <= set(m) for m in got)
    assert got[0]["zones"] == ["Lab"] and got[1]["zones"] == []
    refused = [q for q in receiver.requests if q.status == 503]
    assert len(refused) == 2, "the receiver did not refuse twice: the retry was not exercised"
    ok = [q for q in receiver.requests if q.status == 200]
    assert all(valid_signature(q, SECRET) for q in receiver.requests)
    # a retry carries the id and the body of the attempt it repeats
    first = receiver.requests[0]
    assert [q.header("webhook-id") for q in receiver.requests[:3]] == [
        first.header("webhook-id")
    ] * 3
    assert ok[0].body == first.body
    status = drained(client, admin, site_id, "hook")
    assert status["delivered"] == 2 and status["failed"] == 0 and status["last_ok_at"]
    assert status["last_error"] is None


@needs_broker
def test_every_position_is_published_and_the_zone_state_retained(
    client: TestClient, admin: dict, site_id: str, settings: Settings
) -> None:
    prefix = f"t{site_id}"
    sub = Subscriber(f"{prefix}/#")
    try:
        body = {"kind": "mqtt", "url": "mqtt://127.0.0.1:1883", "topic_prefix": prefix}
        assert client.put(f"/v1/sites/{site_id}/outputs/mq", json=body, headers=admin).is_success
        after_refresh(settings)
        r = client.post("/v1/ingest?wait=true", json=walk(site_id, "tag1"), headers=admin)
        stored = stored_positions(client, admin, site_id, "tag1")
        assert len(stored) >= 30, r.text
        topic = f"{prefix}/{site_id}/devices/tag1/position"
        until(lambda: len(sub.on(topic)) >= len(stored))
        assert [m["t"] for m in sub.on(topic)] == stored  # each once, in order
        events = f"{prefix}/{site_id}/zones/Lab/events"
        until(lambda: len(sub.on(events)) == 2)
    finally:
        sub.close()
    # a fresh subscriber gets the retained zone state at once
    late = Subscriber(f"{prefix}/{site_id}/devices/tag1/zone")
    try:
        (state,) = until(lambda: late.on(f"{prefix}/{site_id}/devices/tag1/zone"), 10)
    finally:
        late.close()
    assert state["zones"] == [] and isinstance(state["t"], int)


@needs_broker
def test_home_assistant_discovery_announces_each_device_once_retained(
    client: TestClient, admin: dict, site_id: str, settings: Settings
) -> None:
    prefix = f"ha{site_id}"
    device = f"{prefix}/{site_id}/devices/tag-ha"
    # the object id keeps letters, digits, _ and -
    config_topic = f"homeassistant/device_tracker/locus_{site_id}_tag-ha/config"
    sub = Subscriber(f"{prefix}/#", config_topic)
    try:
        body = {"kind": "mqtt", "url": "mqtt://127.0.0.1:1883", "topic_prefix": prefix}
        plain = client.put(f"/v1/sites/{site_id}/outputs/ha", json=body, headers=admin)
        assert plain.json()["home_assistant"] is False
        on = client.put(
            f"/v1/sites/{site_id}/outputs/ha", json=body | {"home_assistant": True}, headers=admin
        )
        assert on.status_code == 200 and on.json()["home_assistant"] is True, on.text
        after_refresh(settings)
        client.post("/v1/ingest?wait=true", json=walk(site_id, "tag-ha"), headers=admin)
        stored = stored_positions(client, admin, site_id, "tag-ha")
        until(lambda: len(sub.on(f"{device}/position")) >= len(stored))
        # announced once on the connection, before the device's first state
        assert len(sub.on(config_topic)) == 1
        first = [p.topic for p in sub.received].index(config_topic)
        assert first < [p.topic for p in sub.received].index(f"{device}/position")
    finally:
        sub.close()
    late = Subscriber(config_topic, f"{device}/zone")
    try:
        until(lambda: len(late.received) == 2, 10, "the retained config and zone state")
    finally:
        late.close()
    assert all(p.retained for p in late.received)
    (config,) = late.on(config_topic)
    assert config["state_topic"] == f"{device}/zone"
    assert config["json_attributes_topic"] == f"{device}/position"
    assert "value_json.accuracy" in config["json_attributes_template"]
    assert "value_json.zones[0]" in config["value_template"]
    assert config["unique_id"] == config_topic.split("/")[2]
    assert config["device"]["identifiers"] == [config["unique_id"]]
    (state,) = late.on(f"{device}/zone")
    assert state == {"zones": [], "t": state["t"]}


def test_a_rate_limit_spreads_delivery_to_at_most_its_rate(
    client: TestClient, admin: dict, site_id: str, receiver: Receiver, settings: Settings
) -> None:
    rate = 8.0
    body = {"kind": "webhook", "url": receiver.url, "secret": SECRET, "events": ["position"]}
    r = client.put(
        f"/v1/sites/{site_id}/outputs/slow", json=body | {"rate_limit": rate}, headers=admin
    )
    assert r.json()["rate_limit"] == rate, r.text
    after_refresh(settings)
    client.post("/v1/ingest?wait=true", json=walk(site_id, "rated"), headers=admin)
    stored = stored_positions(client, admin, site_id, "rated")
    assert len(stored) >= 30
    until(lambda: len(receiver.accepted()) >= len(stored), 60)
    assert [m["t"] for m in receiver.accepted()] == stored
    sizes = [len(q.messages) for q in receiver.requests]
    assert max(sizes) <= rate  # no POST carries more than a second's worth
    # a token bucket of one second's messages: after the first second's burst, POSTs leave
    # at the rate (counted from the second POST, which the bucket timed: the first one's
    # arrival also holds the connection's opening)
    later = receiver.requests[1:]
    carried = sum(len(q.messages) for q in later[1:])
    span = later[-1].at - later[0].at
    assert carried >= 2 * rate and carried / span <= rate * 1.1, (carried, span)


def test_a_slow_receiver_gets_the_backlog_in_batches_in_order(
    client: TestClient, admin: dict, site_id: str, receiver: Receiver, settings: Settings
) -> None:
    receiver.delay_s = 1.0
    body = {"kind": "webhook", "url": receiver.url, "secret": SECRET, "events": ["position"]}
    put = client.put(
        f"/v1/sites/{site_id}/outputs/batched", json=body | {"batch_max": 12}, headers=admin
    )
    assert put.json()["batch_max"] == 12, put.text
    after_refresh(settings)
    walked = walk(site_id, "streamer")
    for k in range(0, len(walked["uwb_fix"]), 2):  # two fixes a batch, every 0.1 s
        part = walked | {"uwb_fix": walked["uwb_fix"][k : k + 2]}
        assert client.post("/v1/ingest?wait=true", json=part, headers=admin).status_code == 200
        time.sleep(0.1)
    stored = stored_positions(client, admin, site_id, "streamer")
    until(lambda: len(receiver.accepted()) >= len(stored), 60)
    assert [m["t"] for m in receiver.accepted()] == stored  # each once, in order
    sizes = [len(q.messages) for q in receiver.requests]
    # what waited while the receiver answered went together, a batch_max at most
    assert 1 < max(sizes) <= 12 and len(sizes) <= len(stored) / 3, sizes
    batches = [q for q in receiver.requests if isinstance(json.loads(q.body), list)]
    assert batches and all(valid_signature(q, SECRET) for q in receiver.requests)
    assert drained(client, admin, site_id, "batched")["delivered"] == len(stored)
    # delivery's bookkeeping (leases, acknowledgements) is not a change of the output
    after = client.get(f"/v1/sites/{site_id}/outputs/batched", headers=admin).json()
    assert after["updated_at"] == put.json()["updated_at"]
