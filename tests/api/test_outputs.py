"""Outputs: validation and secrets, and delivery to a real webhook receiver and the
machine's real Mosquitto (skipped, saying so, where no broker answers on 127.0.0.1:1883)."""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from fastapi.testclient import TestClient

T0 = 1_700_000_000_000
SECRET = "whsec_" + base64.b64encode(b"0123456789abcdef0123456789abcdef").decode()


def walk(site_id: str, device: str) -> dict[str, Any]:
    """A tag walking east along y = 4 through the Lab zone (12 <= x <= 16) and out."""
    fixes = [
        {"t": T0 + 200 * k, "x": 10.5 + 0.25 * k, "y": 4.0, "floor_id": "G", "std": 0.1}
        for k in range(38)
    ]
    return {"device_id": device, "site_id": site_id, "uwb_fix": fixes}


def until(condition: Callable[[], Any], timeout: float = 30.0) -> Any:
    """Poll ``condition`` until it is truthy; fail at the deadline."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError("condition not met before the deadline")


class Receiver:
    """A real HTTP server on a free loopback port that records every POST; it answers 503
    until ``refuse_until`` (monotonic seconds)."""

    def __init__(self) -> None:
        self.requests: list[dict[str, Any]] = []
        self.refuse_until = 0.0
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 (the stdlib's name)
                body = self.rfile.read(int(self.headers["content-length"]))
                status = 503 if time.monotonic() < receiver.refuse_until else 200
                receiver.requests.append(
                    {"headers": dict(self.headers.items()), "body": body, "status": status}
                )
                self.send_response(status)
                self.send_header("content-length", "0")
                self.end_headers()

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def accepted(self) -> list[Any]:
        """Return every message of every acknowledged POST, in arrival order."""
        out: list[Any] = []
        for r in self.requests:
            if r["status"] == 200:
                doc = json.loads(r["body"])
                out.extend(doc if isinstance(doc, list) else [doc])
        return out


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    server = Receiver()
    yield server
    server.server.shutdown()


def valid_signature(request: dict[str, Any], secret: str) -> bool:
    """Check a request by the Standard Webhooks formula, independently of Locus's code."""
    h = {k.lower(): v for k, v in request["headers"].items()}
    key = base64.b64decode(secret.removeprefix("whsec_"))
    signed = f"{h['webhook-id']}.{h['webhook-timestamp']}.".encode() + request["body"]
    expected = base64.b64encode(hmac.new(key, signed, hashlib.sha256).digest()).decode()
    return h["webhook-signature"] == f"v1,{expected}"


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


def test_zone_events_reach_a_webhook_signed_and_after_a_refusal(
    client: TestClient, admin: dict, site_id: str, receiver: Receiver
) -> None:
    body = {"kind": "webhook", "url": receiver.url, "secret": SECRET, "events": ["zone"]}
    assert client.put(f"/v1/sites/{site_id}/outputs/hook", json=body, headers=admin).is_success
    time.sleep(2.5)  # workers read a site's outputs again every output_refresh_s (2 s)
    receiver.refuse_until = time.monotonic() + 3.0
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
    refused = [q for q in receiver.requests if q["status"] == 503]
    assert refused, "the receiver refused nothing: the retry was not exercised"
    ok = [q for q in receiver.requests if q["status"] == 200]
    assert all(valid_signature(q, SECRET) for q in receiver.requests)
    # a retry carries the id of the attempt it repeats
    assert refused[0]["headers"]["webhook-id"] == ok[0]["headers"]["webhook-id"]
    status = until(
        lambda: (
            (s := client.get(f"/v1/sites/{site_id}/outputs/hook", headers=admin).json()["status"])[
                "pending"
            ]
            == 0
            and s
        )
    )
    assert status["delivered"] == 2 and status["failed"] == 0 and status["last_ok_at"]


def _broker() -> bool:
    try:
        socket.create_connection(("127.0.0.1", 1883), timeout=1).close()
        return True
    except OSError:
        return False


@pytest.mark.skipif(not _broker(), reason="no MQTT broker answers on 127.0.0.1:1883")
def test_every_position_is_published_and_the_zone_state_retained(
    client: TestClient, admin: dict, site_id: str
) -> None:
    prefix = f"t{site_id}"
    received: list[tuple[str, dict]] = []
    sub = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    sub.on_message = lambda c, u, m: received.append((m.topic, json.loads(m.payload)))
    sub.connect("127.0.0.1", 1883)
    sub.subscribe(f"{prefix}/#", qos=1)
    sub.loop_start()
    try:
        body = {"kind": "mqtt", "url": "mqtt://127.0.0.1:1883", "topic_prefix": prefix}
        assert client.put(f"/v1/sites/{site_id}/outputs/mq", json=body, headers=admin).is_success
        time.sleep(2.5)  # the workers' output_refresh_s
        r = client.post("/v1/ingest?wait=true", json=walk(site_id, "tag1"), headers=admin)
        stored = client.get(
            f"/v1/sites/{site_id}/devices/tag1/positions?limit=1000", headers=admin
        ).json()["items"]
        assert len(stored) >= 30, r.text
        topic = f"{prefix}/{site_id}/devices/tag1/position"
        until(lambda: len([t for t, _ in received if t == topic]) >= len(stored))
        published = [m["t"] for t, m in received if t == topic]
        assert published == [p["t"] for p in stored]  # each once, in order
        events = f"{prefix}/{site_id}/zones/Lab/events"
        until(lambda: len([t for t, _ in received if t == events]) == 2)
    finally:
        sub.loop_stop()
        sub.disconnect()
    # a fresh subscriber gets the retained zone state at once
    fresh: list[dict] = []
    late = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    late.on_message = lambda c, u, m: fresh.append(json.loads(m.payload))
    late.connect("127.0.0.1", 1883)
    late.subscribe(f"{prefix}/{site_id}/devices/tag1/zone", qos=1)
    late.loop_start()
    try:
        state = until(lambda: fresh and fresh[0], 10)
    finally:
        late.loop_stop()
        late.disconnect()
    assert state["zones"] == [] and isinstance(state["t"], int)
