"""The positioning methods compared on site1, built from what was learned, ready to replay walks.

- ``wknn``: WKNN per WiFi scan on the radio maps, no tracking (the peer baseline);
- ``hmm``: the fingerprint + inertial HMM of CN106028450 over the same maps, fed by PDR;
- ``pf``: the particle filter of Eurasian patent 047000 (floor selection, PDR steps, map
  constraint) through ``PositioningEngine`` with the server's default
  parameters, on the transmitters calibrated by ``app.engine.calibration``,
  as on a site without radio maps: floors are chosen on the transmitter
  table alone;
- ``pf-radiomap``: the same where the site has radio maps, as the server
  runs it: the maps' surveyed RSSI in the filters' rasters and in the
  floor evidence.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Protocol

import numpy as np

from app.datasets.ilc import Walk
from app.engine.floors.evidence import FloorEvidence
from app.engine.hmm.emission import EmissionModel
from app.engine.hmm.tracker import HmmTracker
from app.engine.particle.floor_model import FloorModel, build_floor_models
from app.engine.positioning import (
    ParticleTracker,
    PositioningEngine,
    PositioningParams,
    floor_evidence,
    seed_from_id,
)
from app.engine.radiomap import RadioMap
from app.engine.samples import Estimate
from app.engine.wknn import Fingerprints, WknnTracker
from app.evaluation.ilc.learn import Learned, remap
from app.evaluation.ilc.recordings import SiteRecordings, walk_batches
from app.evaluation.ilc.replay import WalkReplay, replay, replay_devices

METHODS = ("wknn", "hmm", "pf", "pf-radiomap")
"""Methods compared. ``pf-radiomap`` is the particle filter whose expected-RSSI
rasters hold the radio maps' surveyed means where the survey went."""

PARTICLE_FILTERS = ("pf", "pf-radiomap")
"""The methods run by ``PositioningEngine``, which can replay many walks at once."""


class WalkRunner(Protocol):
    """A method ready to replay walks one at a time."""

    def __call__(self, site: SiteRecordings, walk: Walk) -> WalkReplay:
        """Replay one walk."""
        ...


def make_runner(name: str, learned: Learned) -> WalkRunner:
    """Return the replay function of a method, with its shared, prebuilt models."""
    if name == "wknn":
        params = learned.tuning.wknn()
        prints = Fingerprints(learned.maps, params.missing_dbm)

        def run_wknn(site: SiteRecordings, walk: Walk) -> WalkReplay:
            return replay(WknnTracker(prints, params), walk_batches(site, walk))

        return run_wknn
    if name == "hmm":
        # the constants a server takes from its site's radio-map build
        hmm_params = learned.tuning.hmm()
        model = EmissionModel(learned.maps, hmm_params)

        def run_hmm(site: SiteRecordings, walk: Walk) -> WalkReplay:
            tracker = HmmTracker(model, hmm_params, learned.pdr)
            return replay(tracker, walk_batches(site, walk))

        return run_hmm
    if name in PARTICLE_FILTERS:
        pf_params = pf_positioning_params(name, learned)
        models = pf_models(name, learned, pf_params)
        evidence = pf_evidence(name, learned, pf_params)

        def run_pf(site: SiteRecordings, walk: Walk) -> WalkReplay:
            tracker = ParticleTracker(
                learned.pf_site,
                pf_params,
                seed=seed_from_id(walk.walk_id),
                models=models,
                evidence=evidence,
            )
            return replay(
                tracker,
                walk_batches(site, walk),
                transform=lambda b: remap(b, learned.pf_lookup),
                flush=tracker.flush,
            )

        return run_pf
    raise ValueError(f"unknown method {name!r}; choose from {', '.join(METHODS)}")


def pf_radio_maps(learned: Learned) -> tuple[RadioMap, ...]:
    """Return the radio maps with their columns renumbered to the particle filter's table."""
    out = []
    for m in learned.maps:
        rows = learned.pf_lookup[m.tx]
        kept = np.flatnonzero(rows >= 0)
        out.append(
            replace(
                m,
                tx=rows[kept].astype(np.int32),
                mean=m.mean[:, kept],
                var=m.var[:, kept],
                detect=m.detect[:, kept],
            )
        )
    return tuple(out)


def pf_positioning_params(name: str, learned: Learned) -> PositioningParams:
    """Return the server's parameters with the learned PDR constants.

    ``pf-radiomap`` also gets the radius floor a server takes from its site's
    radio-map build (``app.workers.trackers.SiteEngines.for_site``).
    """
    floor = learned.tuning.accuracy_floor_m if name == "pf-radiomap" else 0.0
    return PositioningParams(pdr=learned.pdr, accuracy_floor_m=floor)


def pf_models(name: str, learned: Learned, params: PositioningParams) -> tuple[FloorModel, ...]:
    """Return the floor models of ``pf`` (path loss only) or ``pf-radiomap``."""
    maps = pf_radio_maps(learned) if name == "pf-radiomap" else ()
    return build_floor_models(learned.pf_site, params.filter, maps)


def pf_evidence(name: str, learned: Learned, params: PositioningParams) -> FloorEvidence:
    """Return the floor evidence of ``pf`` (transmitter table only) or ``pf-radiomap``."""
    maps = pf_radio_maps(learned) if name == "pf-radiomap" else ()
    return floor_evidence(learned.pf_site, params.floors, maps)


def pf_engine(name: str, learned: Learned) -> PositioningEngine:
    """Return an engine running ``pf`` or ``pf-radiomap`` for many devices at once."""
    params = pf_positioning_params(name, learned)
    return PositioningEngine(
        learned.pf_site,
        params,
        pf_models(name, learned, params),
        pf_evidence(name, learned, params),
    )


def replay_pf_batched(
    site: SiteRecordings,
    learned: Learned,
    walks: Sequence[Walk],
    progress: Callable[[int], None] = lambda _i: None,
    name: str = "pf",
) -> tuple[list[list[Estimate]], float, int]:
    """Replay all walks at once as devices of one ``PositioningEngine``, as a server worker does.

    Returns each walk's estimates (the same as replaying it alone), the
    engine's CPU time (s) and the number of device updates.
    """
    result = replay_devices(
        pf_engine(name, learned),
        {w.walk_id: walk_batches(site, w) for w in walks},
        transform=lambda b: remap(b, learned.pf_lookup),
        progress=progress,
    )
    return [result.estimates[w.walk_id] for w in walks], result.cpu_s, result.updates
