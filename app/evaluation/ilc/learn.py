"""What the positioning methods learn from a site's training walks, and nothing else.

The radio maps, each transmitter's calibrated floor, position and path loss,
the radio maps' cross-validated error and the PDR constants all come from the
training walks only, so the held-out walks are never seen before they are
replayed.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from app.datasets.ilc import floor_level
from app.engine.calibration import CalibrationParams, TransmitterFit, calibrate, to_emitters
from app.engine.crossval import cross_validate
from app.engine.hmm.params import HmmParams
from app.engine.pdr import PdrParams
from app.engine.radiomap import RadioMap, RadioMapParams, Survey, build_radio_map
from app.engine.samples import Batch, RssiReadings
from app.engine.site import Floor, SiteModel
from app.engine.tuning import (
    EMISSION_WEIGHT_CANDIDATES,
    WKNN_K_CANDIDATES,
    SiteTuning,
    tune_site,
)
from app.engine.wknn import WknnParams
from app.evaluation.ilc.recordings import SiteRecordings, survey_of
from app.evaluation.pdr_eval import measure_walks

FLOOR_HEIGHT_M = 4.0
"""Storey height of the site model: ILC carries no survey of it (only z0 of outputs uses it)."""


@dataclass(frozen=True, eq=False)
class Learned:
    """Everything the methods learned from the training walks.

    ``pf_lookup`` maps a site transmitter index to its row in the particle
    filter's transmitter table (-1: not calibrated, unknown to the filter).
    ``tuning`` holds the constants chosen on the training walks by the same
    functions a radio-map build runs (walk-level folds, PDR against waypoints).
    """

    maps: tuple[RadioMap, ...]
    fits: tuple[TransmitterFit, ...]
    pdr: PdrParams
    pf_site: SiteModel
    pf_lookup: np.ndarray
    tuning: SiteTuning


def radio_maps(site: SiteRecordings, srv: Survey, params: RadioMapParams) -> tuple[RadioMap, ...]:
    """Build one radio map per floor (on its walkable area) from the training survey."""
    return tuple(
        build_radio_map(srv, f, params, walkable=site.plans[f]) for f in range(len(site.floors))
    )


def pf_site_model(
    site: SiteRecordings, fits: Sequence[TransmitterFit]
) -> tuple[SiteModel, np.ndarray]:
    """Return the particle filter's site (plausible calibrated transmitters only) and the lookup.

    Transmitters whose fit is implausible or missing are not in the table:
    the server only knows transmitters with a path-loss model, and the
    filter's floor selection needs every heard transmitter's floor.
    """
    kept = [f for f in fits if f.plausible]
    lookup = np.full(len(site.tx_ids), -1, dtype=np.int64)
    lookup[[f.tx for f in kept]] = np.arange(len(kept))
    renumbered = [replace(f, tx=i) for i, f in enumerate(kept)]
    emitters = to_emitters(renumbered, tuple(site.tx_ids[f.tx] for f in kept))
    floors = tuple(
        Floor(name, floor_level(name), FLOOR_HEIGHT_M, plan, FLOOR_HEIGHT_M * i)
        for i, (name, plan) in enumerate(zip(site.floors, site.plans, strict=True))
    )
    return SiteModel("ilc-site1", floors, emitters), lookup


def remap(batch: Batch, lookup: np.ndarray) -> Batch:
    """Return the batch with transmitter indices mapped through ``lookup``; -1 dropped.

    Turns a batch in the site's transmitter table into one in the particle
    filter's (``pf_site_model``'s lookup).
    """
    r = batch.rssi
    tx = lookup[r.tx] if r.tx.size else np.zeros(0, np.int64)
    keep = tx >= 0
    readings = RssiReadings(t=r.t[keep], tx=tx[keep].astype(np.int32), rssi=r.rssi[keep])
    return replace(batch, rssi=readings)


def learn(
    site: SiteRecordings,
    train_ids: Sequence[str],
    *,
    map_params: RadioMapParams | None = None,
    calibration: CalibrationParams | None = None,
    pdr: PdrParams | None = None,
    status: Callable[[str], None] = lambda _: None,
) -> Learned:
    """Learn the radio maps, transmitter calibration and PDR constants from ``train_ids``."""
    chosen = set(train_ids)
    status("locating training scans")
    srv = survey_of(site, chosen)
    status("building radio maps")
    maps = radio_maps(site, srv, map_params or RadioMapParams())
    status("cross-validating the radio maps and choosing the site's constants")
    validation = cross_validate(
        srv,
        dict(enumerate(site.plans)),
        map_params or RadioMapParams(),
        WknnParams(),
        ks=WKNN_K_CANDIDATES,
        emission=HmmParams(),
        weights=EMISSION_WEIGHT_CANDIDATES,
    )
    status("calibrating transmitters")
    fits = tuple(calibrate(srv, calibration or CalibrationParams()))
    status("fitting PDR constants")
    training_walks = (w for w in site.walks if w.walk_id in chosen)
    tuning = tune_site(measure_walks(training_walks, PdrParams()), validation)
    model, lookup = pf_site_model(site, fits)
    return Learned(maps, fits, tuning.pdr(pdr), model, lookup, tuning)
