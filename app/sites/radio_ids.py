"""The key under which a radio sample's transmitter id is looked up in a site's table."""

from __future__ import annotations


def radio_id(kind: str, raw: str) -> str:
    """Return the transmitter table key of a radio sample id of ``kind`` (``wifi`` or ``ble``)."""
    # MAC addresses are case-insensitive; iBeacon ids are UUID_major_minor as given.
    return raw.lower() if kind == "wifi" or ":" in raw else raw
