"""Webhook signatures as the Standard Webhooks specification defines them.

The signed content is ``"{webhook-id}.{webhook-timestamp}.{body}"``; the
signature is the base64 of its HMAC-SHA256 under the secret's key bytes, sent
as ``webhook-signature: v1,<signature>``. A secret ``whsec_<base64>`` (the
specification's form) has the decoded bytes as its key; any other secret its
UTF-8 bytes.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac

PREFIX = "whsec_"


def signing_key(secret: str) -> bytes:
    """Return the HMAC key of a secret; a ``whsec_`` secret that is not base64 is refused."""
    if secret.startswith(PREFIX):
        try:
            key = base64.b64decode(secret[len(PREFIX) :], validate=True)
        except binascii.Error:
            raise ValueError("a whsec_ secret must be followed by base64") from None
        if not key:
            raise ValueError("a whsec_ secret must not be empty")
        return key
    return secret.encode()


def signature(key: bytes, message_id: str, timestamp: int, body: bytes) -> str:
    """Return the ``webhook-signature`` header value of a body sent at ``timestamp`` (s)."""
    content = f"{message_id}.{timestamp}.".encode() + body
    digest = hmac.new(key, content, hashlib.sha256).digest()
    return "v1," + base64.b64encode(digest).decode()


def headers(key: bytes, message_id: str, timestamp: int, body: bytes) -> dict[str, str]:
    """Return the three signature headers of a webhook request."""
    return {
        "webhook-id": message_id,
        "webhook-timestamp": str(timestamp),
        "webhook-signature": signature(key, message_id, timestamp, body),
        "content-type": "application/json",
    }
