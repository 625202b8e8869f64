"""The phone engine stage by stage, in process, on the site a server built.

After a through-server run, the site is read from that server's database and
assembled as its workers assemble it (``assemble_site``, then
``SiteEngines.for_site``: the same transmitter table, radio maps, learned
PDR constants, HMM weights and radius calibration). Every held-out walk then
goes, in the same one-second batches as the HTTP replay, through the
ingest's screening (``screen_batch``) and a worker's ``DeviceSession``: the
same per-sample drops, sample conversion, late rule, filter choice,
fixed-lag smoother and emission rules. Each stage is scored on its own:

- the per-scan k-NN on the build's own survey scans, no tracking;
- the HMM's live positions;
- those refined by the fixed-lag smoother, as the history serves them (the
  refined position wherever there is one) right after the walk's last batch:
  the server's row, computed here;
- the live track refined by the full backward pass (``smooth_track``).

CPU per update is the filter's own time per batch (``process_time``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from sqlalchemy import create_engine
from sqlalchemy.orm import Session

from app.core.config import Settings
from app.datasets.ilc import Walk
from app.engine.samples import Estimate
from app.engine.smoothing import smooth_track
from app.evaluation.ilc.knn_baseline import scan_estimates
from app.evaluation.ilc.score import (
    Row,
    WalkScore,
    estimates_from_positions,
    score_walk,
    summarise,
)
from app.importers.ilc import walk_samples
from app.ingest.service import batch_samples, screen_batch
from app.replay import batches_by_time
from app.sites.assembly import assemble_site
from app.sites.models import Site
from app.workers.device import DeviceSession
from app.workers.trackers import SiteEngines

STAGES = (
    "k-NN on the build's scans",
    "+ HMM tracking (live)",
    "+ fixed-lag smoothing",
    "+ full smoothing",
)
"""The rows, in the order each stage is added."""


@dataclass
class StageScores:
    """Every stage's walk scores, the tracker's CPU time (s) and batch count, and the kept
    walks' estimates by stage (floors numbered as the evaluation numbers them)."""

    scores: dict[str, list[WalkScore]]
    cpu_s: float
    updates: int
    tracks: dict[str, dict[str, list[Estimate]]] = field(default_factory=dict)

    def rows(self) -> list[Row]:
        """Return one table row per stage; CPU per update on the tracking rows."""
        return [
            summarise(
                name,
                self.scores[name],
                0.0 if i == 0 else self.cpu_s,
                0 if i == 0 else self.updates,
            )
            for i, name in enumerate(STAGES)
        ]


def load_engines(database_url: str, site_id: str, settings: Settings) -> SiteEngines:
    """Assemble the stored site exactly as a worker does, warmed as a worker warms it (its
    compiled loops loaded before the first device, not counted in a device's update)."""
    engine = create_engine(database_url)
    try:
        with Session(engine) as db:
            site = db.get(Site, site_id)
            if site is None:
                raise LookupError(f"site '{site_id}' is not in {database_url}")
            loaded = assemble_site(db=db, site=site, raster_cell=settings.raster_cell)
    finally:
        engine.dispose()
    return SiteEngines.for_site(loaded).warm()


def _renumbered(estimates: Sequence[Estimate], floors: np.ndarray) -> list[Estimate]:
    """Return the estimates with their floor index mapped through ``floors``."""
    return [replace(e, floor=int(floors[e.floor])) for e in estimates]


def served_track(emitted: Sequence[Estimate]) -> list[Estimate]:
    """Return what the history serves: refined positions up to the last refined time, then
    live ones, one per time."""
    refined = {e.t: e for e in emitted if e.smoothed}
    until = max(refined, default=-1)
    live = {e.t: e for e in emitted if not e.smoothed and e.t > until}
    return [(refined | live)[t] for t in sorted(refined | live)]


def replay_stages(
    engines: SiteEngines,
    site_id: str,
    walks: Sequence[Walk],
    floors: Sequence[str],
    *,
    wifi_times: str,
    settings: Settings,
    keep: Collection[str] = (),
) -> StageScores:
    """Replay ``walks`` through worker device sessions and score every stage; each batch is
    screened as the ingest screens it (``settings``' limits); the estimates of the walks
    named in ``keep`` are kept, by stage."""
    # the site numbers floors by its own order; scores use ``floors``'
    to_eval = np.array([floors.index(f) for f in engines.site.floor_ids], dtype=np.int64)
    scores: dict[str, list[WalkScore]] = {name: [] for name in STAGES}
    tracks: dict[str, dict[str, list[Estimate]]] = {}
    cpu = 0.0
    updates = 0
    for walk in walks:
        device_id = f"stages-{walk.walk_id}"
        session = DeviceSession(device_id=device_id, engines=engines, now=0)
        chunks = batches_by_time(
            walk_samples(walk, wifi_times=wifi_times),
            batch_ms=1000,
            sent_at={"wifi": walk.wifi.t.tolist()},
        )
        knn: list[Estimate] = []
        live: list[Estimate] = []
        messages: list[dict[str, Any]] = []
        for chunk in chunks:
            body = json.dumps({"device_id": device_id, "site_id": site_id} | chunk)
            batch_in, _ = screen_batch(body, settings)
            session.add(batch_samples(batch_in), now=0)
            batch, _ = session.take(reorder_ms=0, flush=True)
            if batch is None or session.tracker is None:
                continue
            if engines.hmm.references is not None:
                knn += scan_estimates(engines.hmm.references, batch.rssi)
            t0 = time.process_time()
            estimates = session.tracker.process(batch)
            cpu += time.process_time() - t0
            updates += 1
            # what the session emits, each time once; the full pass needs the estimates'
            # own odometry, which messages do not carry
            live += [e for e in estimates if not e.smoothed and e.t > session.emitted_t]
            messages += session.emit(estimates, now=0)[0]
        smoothed = smooth_track(live, engines.site.tuning.full_pass())
        emitted = estimates_from_positions(messages, floors)
        served = served_track(emitted)
        floor = floors.index(walk.floor)
        stages = (
            _renumbered(knn, to_eval),
            [e for e in emitted if not e.smoothed],
            served,
            _renumbered(smoothed, to_eval),
        )
        for name, stage in zip(STAGES, stages, strict=True):
            scores[name].append(score_walk(walk.waypoints, floor, stage))
        if walk.walk_id in keep:
            tracks[walk.walk_id] = dict(zip(STAGES, stages, strict=True))
    return StageScores(scores, cpu, updates, tracks)
