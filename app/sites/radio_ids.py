"""The key under which a radio sample's transmitter id is looked up in a site's table."""

from __future__ import annotations


def radio_id(raw: str) -> str:
    """Return the transmitter table key of a WiFi or BLE sample's id.

    MAC addresses and iBeacon ids (``UUID_major_minor``, the UUID in hex) are both
    case-insensitive, so the key is the lower-case id, as the floor map stores it.
    """
    return raw.lower()
