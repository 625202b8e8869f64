"""A device's identity: the site it belongs to and its id there."""

from __future__ import annotations

DeviceKey = tuple[str, str]
"""(site id, device id). The same device id in two sites is two devices: every store, cache,
stream message and filter that holds device state is keyed by both."""
