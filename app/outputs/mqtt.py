"""Publishing an output's messages to an MQTT broker.

aiomqtt (2.x, on paho-mqtt 2.x) rather than paho-mqtt alone: it is asyncio
native, so the dispatcher awaits QoS 1 acknowledgements on the API's event
loop instead of running paho's network thread and bridging its callbacks, and
it is the maintained asyncio client of the paho project's protocol code.
A batch's messages are handed to paho in order and leave on the connection in
that order; the broker keeps the order of one connection's QoS 1 messages.
"""

from __future__ import annotations

import asyncio
import json
import re
import ssl
from typing import Any
from urllib.parse import urlsplit

import aiomqtt
import paho.mqtt.client as mqtt

from app.outputs.models import OutboxRow

UNSAFE_LEVEL = re.compile(r"[/+#\x00]")
"""What may not appear inside one topic level (a zone's name may hold any of it)."""
UNSAFE_ID = re.compile(r"[^A-Za-z0-9_-]")
"""What Home Assistant does not take in a discovery topic's object id."""


class DeliveryError(Exception):
    """A delivery attempt failed; the message is the reason shown on the output's status."""


def level(name: str) -> str:
    """Return ``name`` safe as one topic level: ``/``, ``+`` and ``#`` become ``_``."""
    return UNSAFE_LEVEL.sub("_", name) or "_"


class MqttSender:
    """One output's connection to its broker, opened when needed and again after a loss."""

    def __init__(
        self,
        *,
        url: str,
        topic_prefix: str,
        username: str | None,
        password: str | None,
        home_assistant: bool,
        client_id: str,
        timeout_s: float,
        batch_max: int,
    ) -> None:
        parts = urlsplit(url)
        self.hostname = parts.hostname or "localhost"
        self.tls = parts.scheme == "mqtts"
        self.port = parts.port or (8883 if self.tls else 1883)
        self.prefix = topic_prefix
        self.username = username or parts.username
        self.password = password
        self.home_assistant = home_assistant
        self.client_id = client_id
        self.timeout_s = timeout_s
        self.batch_max = batch_max
        self.client: aiomqtt.Client | None = None
        self.announced: set[tuple[str, str]] = set()
        """Devices whose Home Assistant discovery this connection has published."""

    async def _connected(self) -> aiomqtt.Client:
        if self.client is None:
            client = aiomqtt.Client(
                self.hostname,
                self.port,
                username=self.username,
                password=self.password,
                identifier=self.client_id,
                timeout=self.timeout_s,
                tls_context=ssl.create_default_context() if self.tls else None,
                # no window: a batch (a bounded number) goes out at once, and the
                # acknowledgements stream back; with paho's 20 the rate was 20 a round trip,
                # and each acknowledgement rescanned every message waiting
                max_inflight_messages=0,
            )
            try:
                await client.__aenter__()
            except aiomqtt.MqttError as exc:
                raise DeliveryError(
                    f"cannot connect to {self.hostname}:{self.port}: {exc}"
                ) from exc
            # a batch's publishes are awaited together (at most three a row, with a discovery):
            # that many waiting is the design, not the backlog aiomqtt warns of
            client.pending_calls_threshold = 3 * self.batch_max
            self.client = client
            self.announced.clear()
        return self.client

    def topics(self, row: OutboxRow, *, announce: bool) -> list[tuple[str, str, bool]]:
        """Return the (topic, payload, retained) publications of one outbox row, first the
        device's Home Assistant discovery when ``announce``."""
        base = f"{self.prefix}/{level(row.site_id)}"
        device = f"{base}/devices/{level(row.device_id)}"
        found: list[tuple[str, str, bool]] = []
        if announce:
            found.append(self._discovery(row.site_id, row.device_id, device))
        if row.kind == "position":
            found.append((f"{device}/position", row.payload, False))
        else:
            message = json.loads(row.payload)  # a position's payload goes as it is
            found.append((f"{base}/zones/{level(message['zone'])}/events", row.payload, False))
            state = {"zones": message.get("zones", []), "t": message["t"]}
            found.append((f"{device}/zone", json.dumps(state, separators=(",", ":")), True))
        return found

    def _discovery(self, site_id: str, device_id: str, device: str) -> tuple[str, str, bool]:
        """Return the retained Home Assistant discovery of a device: a device tracker whose
        state is its first zone (``not_home`` in none), with the position as attributes."""
        unique = UNSAFE_ID.sub("_", f"locus_{site_id}_{device_id}")
        config: dict[str, Any] = {
            "name": device_id,
            "unique_id": unique,
            "state_topic": f"{device}/zone",
            "value_template": "{{ value_json.zones[0] if value_json.zones else 'not_home' }}",
            "json_attributes_topic": f"{device}/position",
            "json_attributes_template": "{{ {'x': value_json.x, 'y': value_json.y, "
            "'floor_id': value_json.floor_id, 'accuracy': value_json.accuracy, "
            "'t': value_json.t} | tojson }}",
            "device": {"identifiers": [unique], "name": device_id, "manufacturer": "Locus"},
        }
        topic = f"homeassistant/device_tracker/{unique}/config"
        return topic, json.dumps(config, separators=(",", ":")), True

    async def send(self, rows: list[OutboxRow]) -> None:
        """Publish the rows at QoS 1 and return once the broker acknowledged every one."""
        client = await self._connected()
        publications: list[tuple[str, str, bool]] = []
        devices: set[tuple[str, str]] = set()
        for row in rows:
            device = (row.site_id, row.device_id)
            # announced once a connection: before the device's first message in it
            announce = self.home_assistant and not (device in self.announced or device in devices)
            devices.add(device)
            publications.extend(self.topics(row, announce=announce))
        *first, (topic, payload, retain) = publications
        try:
            # all but the last go to paho directly, in order: awaiting each through aiomqtt
            # cost two tasks a message, a third of the API process's time at 1,000 a second.
            # A broker acknowledges a connection's QoS 1 messages in the order they came
            # (MQTT 3.1.1, 4.6.0), so the last one's acknowledgement follows every other's;
            # each is checked published then all the same
            sent = [client._client.publish(t, p, qos=1, retain=r) for t, p, r in first]
            if any(info.rc != mqtt.MQTT_ERR_SUCCESS for info in sent):
                raise aiomqtt.MqttError(f"paho refused a publish: {sent[-1].rc}")
            await client.publish(topic, payload, qos=1, retain=retain, timeout=self.timeout_s)
        except (aiomqtt.MqttError, TimeoutError) as exc:
            await self.close()
            raise DeliveryError(f"publish to {self.hostname}:{self.port} failed: {exc}") from exc
        if not all(info.is_published() for info in sent):
            await self.close()
            raise DeliveryError(f"{self.hostname}:{self.port} left a message unacknowledged")
        self.announced |= devices

    async def close(self) -> None:
        """Disconnect (a lost connection is dropped without waiting)."""
        client, self.client = self.client, None
        if client is not None:
            try:
                await asyncio.wait_for(client.__aexit__(None, None, None), self.timeout_s)
            except (aiomqtt.MqttError, TimeoutError):
                pass
