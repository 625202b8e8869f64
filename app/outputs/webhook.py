"""Posting an output's messages to a webhook, signed as Standard Webhooks says."""

from __future__ import annotations

import time

import httpx

from app.outputs.models import OutboxRow
from app.outputs.mqtt import DeliveryError
from app.outputs.signing import headers, signing_key


class WebhookSender:
    """One output's HTTP client: a row alone as a JSON object, a batch as a JSON array."""

    def __init__(self, *, url: str, secret: str, timeout_s: float) -> None:
        self.url = url
        self.key = signing_key(secret)
        self.client = httpx.AsyncClient(timeout=timeout_s)

    async def send(self, rows: list[OutboxRow]) -> None:
        """POST the rows; a 2xx answer acknowledges them, anything else is an error."""
        payloads = [row.payload for row in rows]
        body = (payloads[0] if len(rows) == 1 else "[" + ",".join(payloads) + "]").encode()
        # the batch's first row names it: the same id on every retry of the same batch
        message_id = f"msg_{rows[0].batch or rows[0].id}"
        try:
            answer = await self.client.post(
                self.url,
                content=body,
                headers=headers(self.key, message_id, int(time.time()), body),
            )
        except httpx.HTTPError as exc:
            raise DeliveryError(f"POST {self.url} failed: {type(exc).__name__}") from exc
        if not answer.is_success:
            raise DeliveryError(f"POST {self.url} answered {answer.status_code}")

    async def close(self) -> None:
        """Close the connection pool."""
        await self.client.aclose()
