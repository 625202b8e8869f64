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
- the HMM's live positions with each step as the phone reports it (a second
  session with ``learn_motion`` off);
- the HMM's live positions as the server emits them, the device's heading
  bias and step-length scale learned online (``motion_fit``);
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

KNN = "k-NN on the build's scans"
TRACKING = "+ HMM tracking, steps as the phone reports them (live)"
LIVE = "+ online heading-bias and step-scale states (live)"
FIXED_LAG = "+ fixed-lag smoothing"
FULL = "+ full smoothing"
STAGES = (KNN, TRACKING, LIVE, FIXED_LAG, FULL)
"""The rows, in the order each stage is added; from ``LIVE`` on, the server's engine."""


@dataclass
class StageScores:
    """Every stage's walk scores, the tracker's CPU time (s) and batch count, and the kept
    walks' estimates by stage (floors numbered as the evaluation numbers them)."""

    scores: dict[str, list[WalkScore]]
    cpu_s: float
    updates: int
    tracks: dict[str, dict[str, list[Estimate]]] = field(default_factory=dict)
    reported_cpu_s: float = 0.0
    """The tracker's CPU time (s) with the steps as the phone reports them (``TRACKING``)."""

    def rows(self) -> list[Row]:
        """Return one table row per stage; CPU per update on the tracking rows."""
        cpu = {KNN: 0.0, TRACKING: self.reported_cpu_s}
        return [
            summarise(
                name,
                self.scores[name],
                cpu.get(name, self.cpu_s),
                0 if name == KNN else self.updates,
            )
            for name in STAGES
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
    as_reported = replace(engines, hmm_params=replace(engines.hmm_params, learn_motion=False))
    served_cpu, reported_cpu, updates = 0.0, 0.0, 0
    for walk in walks:
        chunks = batches_by_time(
            walk_samples(walk, wifi_times=wifi_times),
            batch_ms=1000,
            sent_at={"wifi": walk.wifi.t.tolist()},
        )
        bodies = [
            json.dumps({"device_id": f"stages-{walk.walk_id}", "site_id": site_id} | chunk)
            for chunk in chunks
        ]
        served = _session_replay(engines, bodies, settings, knn=True)
        reported = _session_replay(as_reported, bodies, settings, knn=False)
        served_cpu += served.cpu_s
        reported_cpu += reported.cpu_s
        updates += served.updates
        smoothed = smooth_track(served.live, engines.site.tuning.full_pass())
        emitted = estimates_from_positions(served.messages, floors)
        floor = floors.index(walk.floor)
        stages = (
            _renumbered(served.knn, to_eval),
            [e for e in estimates_from_positions(reported.messages, floors) if not e.smoothed],
            [e for e in emitted if not e.smoothed],
            served_track(emitted),
            _renumbered(smoothed, to_eval),
        )
        for name, stage in zip(STAGES, stages, strict=True):
            scores[name].append(score_walk(walk.waypoints, floor, stage))
        if walk.walk_id in keep:
            tracks[walk.walk_id] = dict(zip(STAGES, stages, strict=True))
    return StageScores(scores, served_cpu, updates, tracks, reported_cpu)


@dataclass
class _SessionReplay:
    """One walk through one device session: the per-scan k-NN's estimates (if asked), the
    live estimates, the position messages emitted, and the tracker's CPU time and batches."""

    knn: list[Estimate] = field(default_factory=list)
    live: list[Estimate] = field(default_factory=list)
    messages: list[dict[str, Any]] = field(default_factory=list)
    cpu_s: float = 0.0
    updates: int = 0


def _session_replay(
    engines: SiteEngines, bodies: Sequence[str], settings: Settings, *, knn: bool
) -> _SessionReplay:
    """Replay one walk's ingest bodies through a worker's device session on ``engines``."""
    out = _SessionReplay()
    session: DeviceSession | None = None
    for body in bodies:
        batch_in, _ = screen_batch(body, settings)
        if session is None:
            session = DeviceSession(device_id=batch_in.device_id, engines=engines, now=0)
        session.add(batch_samples(batch_in), now=0)
        batch, _ = session.take(reorder_ms=0, flush=True)
        if batch is None or session.tracker is None:
            continue
        if knn and engines.hmm.references is not None:
            out.knn += scan_estimates(engines.hmm.references, batch.rssi)
        t0 = time.process_time()
        estimates = session.tracker.process(batch)
        out.cpu_s += time.process_time() - t0
        out.updates += 1
        # what the session emits, each time once; the full pass needs the estimates'
        # own odometry, which messages do not carry
        out.live += [e for e in estimates if not e.smoothed and e.t > session.emitted_t]
        out.messages += session.emit(estimates, now=0)[0]
    return out
