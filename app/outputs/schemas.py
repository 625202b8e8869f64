"""Request and response bodies of the outputs API.

An output is PUT whole: what the body leaves out takes its default. Secrets
(the webhook's signing secret, the MQTT password) are write-only: no answer
carries them, only whether one is set.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, field_validator

EVENT_KINDS = ("position", "zone")
"""What an output may take: each position, and each zone enter/exit."""
MQTT_SCHEMES = ("mqtt", "mqtts")
WEBHOOK_SCHEMES = ("http", "https")
TOPIC_LEVEL = r"^[A-Za-z0-9_.:-]{1,100}(/[A-Za-z0-9_.:-]{1,100}){0,7}$"


def check_url(value: str, schemes: tuple[str, ...], kind: str) -> str:
    """Return ``value`` when it is a URL of one of ``schemes`` with a host and no password."""
    parts = urlsplit(value)
    if parts.scheme not in schemes:
        given = f"the scheme {parts.scheme!r}" if parts.scheme else "no scheme"
        raise ValueError(
            f"a {kind} url must be {' or '.join(s + '://' for s in schemes)}; it has {given}"
        )
    if not parts.hostname:
        raise ValueError(f"the {kind} url has no host")
    if parts.password is not None:
        # a password in the URL would be shown back with it on every read
        raise ValueError("the url must not carry a password; give it in its own field")
    try:
        parts.port  # noqa: B018 (parsing the port is the check)
    except ValueError:
        raise ValueError(f"the {kind} url has an invalid port") from None
    return value


def check_events(value: list[str]) -> list[str]:
    """Return the event kinds without repeats, or refuse one that is unknown."""
    for kind in value:
        if kind not in EVENT_KINDS:
            raise ValueError(f"unknown event kind {kind!r}; use 'position' or 'zone'")
    return sorted(set(value), key=EVENT_KINDS.index)


Events = Annotated[list[str], Field(min_length=1, max_length=2)]
RateLimit = Annotated[
    float | None,
    Field(gt=0, le=100_000, description="Messages per second at most (default: the node's)."),
]


class MqttOutput(BaseModel):
    """Publish to an MQTT broker (QoS 1)."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["mqtt"]
    url: str = Field(max_length=2048, description="mqtt://host:1883 or mqtts://host:8883")
    topic_prefix: str = Field(default="locus", pattern=TOPIC_LEVEL)
    events: Events = ["position", "zone"]
    username: str | None = Field(default=None, max_length=256)
    password: str | None = Field(default=None, max_length=1024)
    home_assistant: bool = Field(
        default=False, description="Also publish Home Assistant MQTT discovery per device."
    )
    rate_limit: RateLimit = None

    @field_validator("url")
    @classmethod
    def _url(cls, value: str) -> str:
        return check_url(value, MQTT_SCHEMES, "mqtt")

    @field_validator("events")
    @classmethod
    def _events(cls, value: list[str]) -> list[str]:
        return check_events(value)


class WebhookOutput(BaseModel):
    """POST signed JSON (Standard Webhooks) to an HTTP endpoint."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["webhook"]
    url: str = Field(max_length=2048, description="http:// or https:// endpoint")
    secret: str = Field(
        min_length=8,
        max_length=1024,
        description="Signing key: whsec_<base64> (the decoded bytes are the key) or any "
        "other string (its UTF-8 bytes are the key).",
    )
    events: Events = ["zone"]
    batch_max: int = Field(
        default=100, ge=1, le=1000, description="Most messages in one POST when a backlog waits."
    )
    rate_limit: RateLimit = None

    @field_validator("url")
    @classmethod
    def _url(cls, value: str) -> str:
        return check_url(value, WEBHOOK_SCHEMES, "webhook")

    @field_validator("events")
    @classmethod
    def _events(cls, value: list[str]) -> list[str]:
        return check_events(value)

    @field_validator("secret")
    @classmethod
    def _secret(cls, value: str) -> str:
        from app.outputs.signing import signing_key

        signing_key(value)  # a whsec_ secret must decode
        return value


OutputUpsert = Annotated[MqttOutput | WebhookOutput, Field(discriminator="kind")]


class OutputStatus(BaseModel):
    """How delivery to an output goes: totals since it was created, and what waits."""

    delivered: int
    pending: int
    failed: int = Field(description="Messages given up after the retention bound.")
    last_error: str | None
    last_ok_at: datetime | None


class OutputRead(BaseModel):
    """An output as stored, without its secret or password."""

    id: str
    site_id: str
    kind: Literal["mqtt", "webhook"]
    url: str
    events: list[str]
    topic_prefix: str | None = None
    username: str | None = None
    home_assistant: bool | None = None
    batch_max: int | None = None
    rate_limit: float | None = None
    has_secret: bool = Field(description="Whether a secret or password is set (never shown).")
    status: OutputStatus
    created_at: datetime
    updated_at: datetime
