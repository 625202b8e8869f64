"""One device inside a worker: reorder buffer, filter, zones, snapshot bookkeeping."""

from __future__ import annotations

import math
from typing import Any

from shapely import Point

from app.core.time import now_ms
from app.engine.samples import Batch, Estimate
from app.engine.tracker import Tracker
from app.sites.assembly import LoadedSite
from app.workers.convert import to_batch


class DeviceSession:
    """A device's live state: samples wait in a reorder window, then feed its filter.

    The filter is chosen when the first samples are released (``tracker`` is
    None until then), since what a device sends decides which filter fits.

    Samples are held until they are ``reorder_ms`` older (in measurement time)
    than the newest sample seen, so batches that overtake each other on the
    network are still used in time order. Older arrivals are counted late.
    """

    def __init__(
        self,
        *,
        device_id: str,
        site: LoadedSite,
        tracker: Tracker | None = None,
        processed_t: int = -1,
        zones: frozenset[str] = frozenset(),
    ) -> None:
        self.device_id = device_id
        self.site = site
        self.tracker = tracker
        self.processed_t = processed_t
        self.max_t = processed_t
        self.zones = zones
        self.buffer: list[tuple[int, str, dict[str, Any]]] = []
        self.seen: set[int] = set()
        self.snapshot_t = processed_t
        self.last_seen_wall = now_ms()
        self.unknown = 0
        self.emitted_t = -1
        self.unflushed = False
        self.kinds: set[str] = set()

    def add(self, samples: dict[str, list[dict[str, Any]]]) -> tuple[int, int, int]:
        """Buffer a batch; return (accepted, late, duplicate) sample counts."""
        accepted = late = duplicate = 0
        for kind, items in samples.items():
            for sample in items:
                t = sample["t"]
                if t <= self.processed_t:
                    late += 1
                    continue
                key = hash((kind, repr(sample)))
                if key in self.seen:
                    duplicate += 1
                    continue
                self.seen.add(key)
                self.buffer.append((t, kind, sample))
                self.max_t = max(self.max_t, t)
                accepted += 1
        self.last_seen_wall = now_ms()
        return accepted, late, duplicate

    def take(self, *, reorder_ms: int, flush: bool) -> Batch | None:
        """Return what is older than the reorder window (all of it on flush), as engine arrays."""
        if not self.buffer:
            return None
        watermark = self.max_t if flush else self.max_t - reorder_ms
        self.buffer.sort(key=lambda item: item[0])
        cut = 0
        while cut < len(self.buffer) and self.buffer[cut][0] <= watermark:
            cut += 1
        if cut == 0:
            return None
        ready, self.buffer = self.buffer[:cut], self.buffer[cut:]
        self.processed_t = ready[-1][0]
        self.seen = {hash((k, repr(s))) for _, k, s in self.buffer}
        grouped: dict[str, list[dict[str, Any]]] = {}
        for _, kind, sample in ready:
            grouped.setdefault(kind, []).append(sample)
        self.kinds |= set(grouped)
        batch, unknown = to_batch(self.site, grouped)
        self.unknown += unknown
        return batch

    def zone_events(self, estimate: Estimate) -> list[dict[str, Any]]:
        """Return enter/exit events for the zones this estimate moved into or out of."""
        if not self.site.zones:
            return []
        inside = frozenset(
            z.name
            for z in self.site.zones
            if z.floor == estimate.floor and z.polygon.contains(Point(estimate.x, estimate.y))
        )
        events = [
            {
                "type": "zone",
                "event": event,
                "zone": name,
                "device_id": self.device_id,
                "site_id": self.site.site_id,
                "floor_id": self.site.floor_ids[estimate.floor],
                "t": estimate.t,
            }
            for event, names in (("exit", self.zones - inside), ("enter", inside - self.zones))
            for name in sorted(names)
        ]
        self.zones = inside
        return events

    def position(self, estimate: Estimate) -> dict[str, Any]:
        """Return the API's position message for an estimate."""
        floor = self.site.model.floors[estimate.floor] if self.site.model.floors else None
        return {
            "type": "position",
            "device_id": self.device_id,
            "site_id": self.site.site_id,
            "floor_id": floor.floor_id if floor else None,
            "t": int(estimate.t),
            "x": round(estimate.x, 3),
            "y": round(estimate.y, 3),
            "z": round(estimate.z, 3),
            "heading": None if math.isnan(estimate.heading) else round(estimate.heading % 360, 2),
            "accuracy": round(estimate.accuracy, 3),
            "speed": None if math.isnan(estimate.speed) else round(estimate.speed, 3),
            "method": estimate.method,
            "computed_at": now_ms(),
        }
