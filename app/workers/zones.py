"""A device's zone membership with a dwell time, so a filter's jitter at a doorway does
not flicker enter/exit events.

A position inside a zone the device is not in starts a candidate entry; the
entry is confirmed once the device has stayed inside for ``dwell_ms`` of
measurement time, and reported at the time it first came in. Exits are
judged the same way. A position back on the confirmed side cancels the
candidate. With a dwell of 0 every crossing is reported at once.
"""

from __future__ import annotations

from typing import Any

ZoneChange = tuple[str, str, int]
"""("enter" or "exit", zone name, measurement time the device crossed)."""


class ZoneTracker:
    """The zones a device is confirmed in, and the crossings waiting for their dwell."""

    def __init__(self, dwell_ms: int) -> None:
        self.dwell_ms = dwell_ms
        self.inside: frozenset[str] = frozenset()
        self.pending: dict[str, int] = {}
        """Zone name → time of the first position on the other side of it."""

    def update(self, t: int, now_inside: frozenset[str]) -> list[ZoneChange]:
        """Take the zones a position at ``t`` lies in; return the changes now confirmed."""
        changes: list[ZoneChange] = []
        for name in sorted(self.inside | now_inside | self.pending.keys()):
            if (name in now_inside) == (name in self.inside):
                self.pending.pop(name, None)
                continue
            since = self.pending.setdefault(name, t)
            if t - since >= self.dwell_ms:
                del self.pending[name]
                changes.append(("enter" if name in now_inside else "exit", name, since))
        self.inside = self.inside.symmetric_difference(name for _, name, _ in changes)
        # exits before entries at the same time, as a device leaves one room for the next
        return sorted(changes, key=lambda c: (c[2], c[0] != "exit", c[1]))

    def snapshot(self) -> dict[str, Any]:
        """Return the zones and pending crossings as snapshot data."""
        return {"zones": sorted(self.inside), "zones_pending": dict(self.pending)}

    def restore(self, state: dict[str, Any]) -> None:
        """Resume from :meth:`snapshot` (a snapshot from before dwell times has no pending)."""
        self.inside = frozenset(str(z) for z in state.get("zones", ()))
        self.pending = {str(k): int(v) for k, v in state.get("zones_pending", {}).items()}
