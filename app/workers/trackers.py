"""Choosing, building and restoring a device's filter.

A device's kind is chosen from its first samples and the site's infrastructure:
UWB ranges or fixes → the UWB + inertial EKF (``uwb``); sightings by fixed
locators → the locator tracker (``locator``); RSSI of transmitters with a
path-loss model → the particle filter (``pf``), whose devices share one
batched engine per site, or, where the site chose the ``hmm`` engine and has a
built radio map, the fingerprint + inertial HMM (``hmm``); otherwise the
weighted centroid.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from app.engine.centroid import CentroidParams, WeightedCentroid
from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.kernels import load_kernels
from app.engine.hmm.params import HmmParams
from app.engine.hmm.tracker import HmmTracker
from app.engine.locator_tracker import LocatorTracker, LocatorTrackerParams
from app.engine.particle.floor_model import build_floor_models
from app.engine.pdr import PdrParams
from app.engine.pdr_kernel import load_kernel as load_pdr_kernel
from app.engine.positioning import PositioningEngine, PositioningParams, floor_evidence
from app.engine.samples import Batch, Estimate, RssiReadings
from app.engine.scans import load_grouping
from app.engine.smoothing import FixedLagSmoother, SmootherParams, load_solver
from app.engine.tracker import Tracker
from app.engine.uwb_tracker import UwbTracker, UwbTrackerParams
from app.sites.assembly import LoadedSite

PF = "pf"
CENTROID = "centroid"
UWB = "uwb"
LOCATOR = "locator"
HMM = "hmm"
RADIO_KINDS = frozenset({PF, HMM, CENTROID})
"""Kinds that position a device from RSSI of the site's transmitters."""


@dataclass(eq=False)
class SiteEngines:
    """The batched engines of one site version, shared by the shards of a process."""

    site: LoadedSite
    params: PositioningParams
    _pf: PositioningEngine | None = field(default=None, repr=False)
    _hmm: EmissionModel | None = field(default=None, repr=False)
    hmm_params: HmmParams = field(default_factory=HmmParams)
    pdr_params: PdrParams = field(default_factory=PdrParams)
    smoother_params: SmootherParams = field(default_factory=SmootherParams)

    @classmethod
    def for_site(cls, site: LoadedSite) -> SiteEngines:
        """Return a site's engines with the constants its radio-map build chose.

        The build learned the site's PDR constants (step length, heading
        offset), the HMM's neighbours, emission weight and heading noise,
        the fixed-lag smoother's fix scale, and the accuracy floor: the
        median held-out error, added in quadrature to the radius each filter
        computes, since the filters know their own uncertainty under the maps,
        not how far the maps are from the truth.
        """
        tuning = site.tuning
        pdr = tuning.pdr()
        return cls(
            site,
            PositioningParams(pdr=pdr, accuracy_floor_m=tuning.accuracy_floor_m),
            hmm_params=tuning.hmm(),
            pdr_params=pdr,
            smoother_params=tuning.fixed_lag(),
        )

    def warm(self) -> SiteEngines:
        """Build now the shared engine the site's new RSSI devices get; return self.

        A worker warms a site when it loads or changes, so the first device
        there does not wait for its rasters.
        """
        # every phone engine detects steps and groups WiFi scans
        load_pdr_kernel()
        load_grouping()
        kind = radio_kind(self.site)
        if kind == PF:
            _warm_particle_filter(self.pf, self.site)
        elif kind == HMM:
            _warm_hmm(self.hmm)
        return self

    @property
    def pf(self) -> PositioningEngine:
        """Return the site's particle-filter engine, built on first use.

        Its expected-RSSI rasters hold the radio maps' surveyed means where the
        site has them, the path-loss model elsewhere; its floor evidence uses
        the maps when every floor has one.
        """
        if self._pf is None:
            model, maps = self.site.model, self.site.radio_maps
            models = build_floor_models(model, self.params.filter, maps)
            evidence = floor_evidence(model, self.params.floors, maps)
            self._pf = PositioningEngine(model, self.params, models, evidence)
        return self._pf

    @property
    def hmm(self) -> EmissionModel:
        """Return the site's radio-map emission tables (shared by its HMM devices), built once."""
        if self._hmm is None:
            plans = {i: floor.plan for i, floor in enumerate(self.site.model.floors)}
            self._hmm = EmissionModel(self.site.radio_maps, self.hmm_params, plans)
        return self._hmm


WARM_UP_DEVICE = "\x00warm-up"
"""A device id no client can send (ids are validated): the throwaway device of a warm-up."""


def _warm_particle_filter(engine: PositioningEngine, site: LoadedSite) -> None:
    """Run a throwaway device through the engine, so its compiled loops are compiled (or
    loaded from their disk cache) now rather than on a real device's first batch."""
    tx = site.model.transmitters
    usable = np.flatnonzero(np.isfinite(tx.A + tx.B + tx.sigma))[:4]
    if usable.size == 0:
        return
    engine.add(WARM_UP_DEVICE)
    try:
        for k in range(3):
            t = np.full(usable.size, 1000 * k, dtype=np.int64)
            rssi = np.full(usable.size, -60.0)
            batch = Batch(rssi=RssiReadings(t=t, tx=usable.astype(np.int32), rssi=rssi))
            engine.process({WARM_UP_DEVICE: batch})
        engine.flush([WARM_UP_DEVICE])
    finally:
        engine.remove(WARM_UP_DEVICE)


def _warm_hmm(model: EmissionModel) -> None:
    """Compare one reading with the survey scans, run the HMM's kernels and smooth two
    positions, so the compiled loops are ready."""
    refs = model.references
    if refs is not None and refs.usable.any():
        one = np.flatnonzero(refs.usable)[:1]
        refs.distances(one, np.array([-60.0]))
        refs.level_offset(one, np.array([-60.0]), np.zeros(1, dtype=np.int64))
    load_kernels()
    load_solver()


class BatchEngine(Protocol):
    """An engine that positions several devices, one batch each, in one call."""

    def process(self, batches: Mapping[str, Batch]) -> dict[str, list[Estimate]]:
        """Consume one time-ordered batch per device; return each device's new estimates."""
        ...

    def flush(self, device_ids: list[str]) -> dict[str, list[Estimate]]:
        """Position the devices' last, incomplete windows; return each device's estimates."""
        ...


class DeviceTracker(Tracker, Protocol):
    """A device's filter as a shard holds it.

    ``kind`` is stored with its snapshot to rebuild it. ``shared_engine`` is the
    site engine the filter lives in, or None when the filter is the device's
    own: devices sharing an engine are processed together, one engine call per
    round of batches.
    """

    @property
    def kind(self) -> str:
        """Return the kind the filter was made as (see ``make_tracker``)."""
        ...

    @property
    def shared_engine(self) -> BatchEngine | None:
        """Return the engine this filter shares with other devices, if any."""
        ...


class EngineDevice:
    """A device whose filter lives in the site's shared particle-filter engine."""

    kind = PF

    def __init__(self, engine: PositioningEngine, device_id: str, state: dict[str, Any] | None):
        self.shared_engine: PositioningEngine = engine
        self.device_id = device_id
        if state is None:
            engine.add(device_id)
        else:
            engine.restore(device_id, state)

    def process(self, batch: Batch) -> list[Estimate]:
        """Process this device alone (a shard batches devices through the shared engine)."""
        return self.shared_engine.process({self.device_id: batch})[self.device_id]

    def flush(self) -> list[Estimate]:
        """Position the last, incomplete window."""
        return self.shared_engine.flush([self.device_id])[self.device_id]

    def snapshot(self) -> dict[str, Any]:
        """Return the device's state in the engine."""
        return self.shared_engine.snapshot(self.device_id)

    def close(self) -> None:
        """Free the device's filters in the engine."""
        self.shared_engine.remove(self.device_id)


OwnFilter = UwbTracker | LocatorTracker | HmmTracker | WeightedCentroid
"""The filters that are objects of their own, one per device."""


class FilterDevice:
    """A device whose filter is its own object (UWB, locator, HMM, centroid).

    With a ``smoother``, every position is re-emitted refined once the
    smoother's lag has passed (marked ``smoothed``), after the live ones.
    """

    shared_engine: None = None

    def __init__(
        self, kind: str, tracker: OwnFilter, smoother: FixedLagSmoother | None = None
    ) -> None:
        self.kind = kind
        self.tracker = tracker
        self.smoother = smoother

    def process(self, batch: Batch) -> list[Estimate]:
        """Consume one time-ordered batch and return the estimates it produced."""
        live = self.tracker.process(batch)
        return live if self.smoother is None else live + self.smoother.push(live)

    def flush(self) -> list[Estimate]:
        """Return the refined positions still held back: the device went quiet.

        The filters keep what they hold for the device's next batch.
        """
        return [] if self.smoother is None else self.smoother.flush()

    def snapshot(self) -> dict[str, Any]:
        """Return the filter's state (and the smoother's, under ``smoother``)."""
        state = self.tracker.snapshot()
        if self.smoother is not None:
            state["smoother"] = self.smoother.snapshot()
        return state

    def close(self) -> None:
        """Nothing to free: the filter holds nothing outside itself."""


def choose_kind(site: LoadedSite, batch: Batch, kinds: set[str]) -> str:
    """Return the filter kind for a device whose first samples (of ``kinds``) are ``batch``."""
    if len(batch.ranges) or len(batch.fixes):
        return UWB
    if "sightings" in kinds:
        return LOCATOR
    if len(batch.rssi):
        return radio_kind(site)
    return CENTROID


def radio_kind(site: LoadedSite) -> str:
    """Return the filter for a device that sends RSSI of the site's transmitters."""
    if site.engine == HMM and site.radio_maps:
        return HMM
    if site.has_pathloss():
        return PF
    return CENTROID


def _hmm_state_fits(model: EmissionModel, state: dict[str, Any]) -> bool:
    """Return whether an HMM snapshot belongs to radio maps shaped like ``model``'s."""
    m = int(state.get("map", -1))
    if m < 0:
        return int(state.get("n_points", 0)) == 0 and len(state["floor_logp"]) == len(model.maps)
    return (
        m < len(model.maps)
        and int(state["n_points"]) == model.n_points(m)
        and len(state["floor_logp"]) == len(model.maps)
    )


def make_tracker(
    kind: str, engines: SiteEngines, device_id: str, state: dict[str, Any] | None
) -> DeviceTracker:
    """Return the device's filter of ``kind``, fresh or restored from its state."""
    if kind == HMM and not engines.site.radio_maps:
        # restored as an HMM device on a site whose radio maps are gone
        kind, state = radio_kind(engines.site), None
    if kind == PF:
        return EngineDevice(engines.pf, device_id, state)
    if kind == HMM:
        model = engines.hmm
        if state is not None and not _hmm_state_fits(model, state):
            # the radio map was rebuilt: the old distribution has no meaning on the new points
            state = None
        if state is not None:
            state = dict(state)
        saved = None if state is None else state.pop("smoother", None)
        tracker = HmmTracker(model, engines.hmm_params, engines.pdr_params, state=state)
        return FilterDevice(HMM, tracker, FixedLagSmoother(engines.smoother_params, saved))
    if kind == UWB:
        return FilterDevice(UWB, UwbTracker(engines.site.model, UwbTrackerParams(), state))
    if kind == LOCATOR:
        return FilterDevice(
            LOCATOR, LocatorTracker(engines.site.model, LocatorTrackerParams(), state)
        )
    return FilterDevice(CENTROID, WeightedCentroid(engines.site.model, CentroidParams(), state))
