"""Choosing, building and restoring a device's filter.

A device's kind is chosen from its first samples and the site's infrastructure:
UWB ranges or fixes → the UWB + inertial EKF (``uwb``); sightings by fixed
locators → the locator tracker (``locator``); RSSI of transmitters with a
path-loss model → the particle filter (``pf``), whose devices share one
batched engine per site; otherwise the weighted centroid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from app.engine.centroid import CentroidParams, WeightedCentroid
from app.engine.ekf import LocatorTracker, LocatorTrackerParams, UwbTracker, UwbTrackerParams
from app.engine.particle import build_floor_models
from app.engine.positioning import PositioningEngine, PositioningParams
from app.engine.samples import Batch, Estimate
from app.engine.tracker import Tracker
from app.workers.sites import LoadedSite

PF = "pf"
CENTROID = "centroid"
UWB = "uwb"
LOCATOR = "locator"


@dataclass(eq=False)
class SiteEngines:
    """The batched engines of one site version, shared by the shards of a process."""

    site: LoadedSite
    params: PositioningParams
    _pf: PositioningEngine | None = field(default=None, repr=False)

    @property
    def pf(self) -> PositioningEngine:
        """Return the site's particle-filter engine, built on first use."""
        if self._pf is None:
            models = build_floor_models(self.site.model, self.params.filter)
            self._pf = PositioningEngine(self.site.model, self.params, models)
        return self._pf


class EngineDevice:
    """A device whose filter lives in a shared batched engine."""

    kind = PF

    def __init__(self, engine: PositioningEngine, device_id: str, state: dict[str, Any] | None):
        self.engine = engine
        self.device_id = device_id
        if state is None:
            engine.add(device_id)
        else:
            engine.restore(device_id, state)

    def process(self, batch: Batch) -> list[Estimate]:
        """Process this device alone (the shard batches devices through the engine instead)."""
        return self.engine.process({self.device_id: batch})[self.device_id]

    def flush(self) -> list[Estimate]:
        """Position the last, incomplete window."""
        return self.engine.flush([self.device_id])[self.device_id]

    def snapshot(self) -> dict[str, Any]:
        """Return the device's state in the engine."""
        return self.engine.snapshot(self.device_id)

    def close(self) -> None:
        """Free the device's filters in the engine."""
        self.engine.remove(self.device_id)


def choose_kind(site: LoadedSite, batch: Batch, kinds: set[str]) -> str:
    """Return the filter kind for a device whose first samples (of ``kinds``) are ``batch``."""
    if len(batch.ranges) or len(batch.fixes):
        return UWB
    if "sightings" in kinds:
        return LOCATOR
    if len(batch.rssi) and site.has_pathloss():
        return PF
    return CENTROID


def make_tracker(
    kind: str, engines: SiteEngines, device_id: str, state: dict[str, Any] | None
) -> Tracker:
    """Return the device's filter of ``kind``, fresh or restored from its state."""
    if kind == PF:
        return EngineDevice(engines.pf, device_id, state)
    if kind == UWB:
        return UwbTracker(engines.site.model, UwbTrackerParams(), state)
    if kind == LOCATOR:
        return LocatorTracker(engines.site.model, LocatorTrackerParams(), state)
    return WeightedCentroid(engines.site.model, CentroidParams(), state)


def kind_of(tracker: Tracker) -> str:
    """Return the kind a tracker was made as."""
    kinds = {EngineDevice: PF, UwbTracker: UWB, LocatorTracker: LOCATOR}
    return kinds.get(type(tracker), CENTROID)
