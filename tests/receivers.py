"""What the outputs' tests deliver to: a real webhook receiver on a loopback port, and a
real MQTT subscriber on the machine's Mosquitto (127.0.0.1:1883)."""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import paho.mqtt.client as mqtt

BROKER = ("127.0.0.1", 1883)
SECRET = "whsec_" + base64.b64encode(b"0123456789abcdef0123456789abcdef").decode()


def until(condition: Callable[[], Any], timeout: float = 30.0, what: str = "condition") -> Any:
    """Poll ``condition`` until it is truthy and return its value; fail at the deadline."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"{what} not met within {timeout:.0f} s")


def broker_answers() -> bool:
    """Return whether an MQTT broker accepts connections on 127.0.0.1:1883."""
    try:
        socket.create_connection(BROKER, timeout=1).close()
        return True
    except OSError:
        return False


@dataclass
class Request:
    """One POST the receiver was sent."""

    at: float
    """Monotonic seconds when it arrived."""
    headers: dict[str, str]
    body: bytes
    status: int

    @property
    def messages(self) -> list[dict[str, Any]]:
        """The messages it carried: one object, or each of an array (a batch)."""
        doc = json.loads(self.body)
        return doc if isinstance(doc, list) else [doc]

    def header(self, name: str) -> str:
        """Return a header by its case-insensitive name."""
        return {k.lower(): v for k, v in self.headers.items()}[name]


class Receiver:
    """A real HTTP server on a free loopback port that records every POST.

    It answers 503 while ``refusing`` and to the next ``refusals`` requests after that,
    else 200; each answer waits ``delay_s`` first (a slow receiver).
    """

    def __init__(self) -> None:
        self.requests: list[Request] = []
        self.refusing = False
        self.refusals = 0
        self.delay_s = 0.0
        self.lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 (the stdlib's name)
                body = self.rfile.read(int(self.headers["content-length"]))
                with receiver.lock:
                    refused = receiver.refusing or receiver.refusals > 0
                    if not receiver.refusing and receiver.refusals > 0:
                        receiver.refusals -= 1
                time.sleep(receiver.delay_s)
                status = 503 if refused else 200
                receiver.requests.append(
                    Request(time.monotonic(), dict(self.headers.items()), body, status)
                )
                self.send_response(status)
                self.send_header("content-length", "0")
                self.end_headers()

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def accepted(self) -> list[dict[str, Any]]:
        """Return every message of every acknowledged POST, in arrival order."""
        return [m for r in list(self.requests) if r.status == 200 for m in r.messages]

    def close(self) -> None:
        """Stop serving."""
        self.server.shutdown()
        self.server.server_close()


def valid_signature(request: Request, secret: str) -> bool:
    """Check a request by the Standard Webhooks formula, independently of Locus's code."""
    key = base64.b64decode(secret.removeprefix("whsec_"))
    signed = f"{request.header('webhook-id')}.{request.header('webhook-timestamp')}.".encode()
    expected = base64.b64encode(hmac.new(key, signed + request.body, hashlib.sha256).digest())
    return request.header("webhook-signature") == f"v1,{expected.decode()}"


@dataclass
class Publication:
    """One MQTT message a subscriber received."""

    topic: str
    payload: Any
    retained: bool


class Subscriber:
    """A paho-mqtt client subscribed (QoS 1) to ``topics`` on the local broker, recording
    what arrives."""

    def __init__(self, *topics: str) -> None:
        self.received: list[Publication] = []
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        self.client.on_message = lambda c, u, m: self.received.append(
            Publication(m.topic, json.loads(m.payload), bool(m.retain))
        )
        subscribed = threading.Event()
        self.client.on_subscribe = lambda *args: subscribed.set()
        self.client.connect(*BROKER)
        self.client.subscribe([(topic, 1) for topic in topics])
        self.client.loop_start()
        if not subscribed.wait(10):
            raise AssertionError(f"the broker did not confirm the subscription to {topics}")

    def on(self, topic: str) -> list[Any]:
        """Return the payloads received on ``topic``, in arrival order."""
        return [p.payload for p in list(self.received) if p.topic == topic]

    def close(self) -> None:
        """Disconnect."""
        self.client.loop_stop()
        self.client.disconnect()
