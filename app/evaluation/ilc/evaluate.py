"""Every method replayed on the held-out walks and scored: the rows of the site1 table.

CPU time is per one-second batch of one device (one device update). The
particle filters replay all walks as devices of one engine, batched as a
server worker runs them; walk by walk the estimates are identical, only the
CPU per update differs.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

from app.datasets.ilc import Walk
from app.engine.samples import Estimate
from app.engine.smoothing import SmootherParams, fixed_lag, smooth_track
from app.evaluation.ilc.learn import Learned
from app.evaluation.ilc.methods import PARTICLE_FILTERS, make_runner, replay_pf_batched
from app.evaluation.ilc.recordings import SiteRecordings
from app.evaluation.ilc.score import Row, score_walk, summarise


@dataclass
class Evaluation:
    """Rows per method, the estimates of the walks kept for plotting and each method's run time."""

    rows: list[Row]
    kept: dict[str, dict[str, list[Estimate]]] = field(default_factory=dict)
    run_s: dict[str, float] = field(default_factory=dict)


SMOOTHERS: dict[str, Callable[[Sequence[Estimate], SmootherParams], list[Estimate]]] = {
    "fixed-lag": fixed_lag,
    "full smoothing": smooth_track,
}
"""The smoothed rows added after a method whose estimates carry odometry."""


def smoothed_rows(
    site: SiteRecordings,
    walks: Sequence[Walk],
    name: str,
    estimates: Sequence[Sequence[Estimate]],
    cpu_s: float,
    updates: int,
    kept: dict[str, dict[str, list[Estimate]]],
) -> list[Row]:
    """Return the rows of a method's estimates refined by each smoother (its CPU added);
    the kept walks' refined estimates go into ``kept``."""
    rows = []
    for label, smoother in SMOOTHERS.items():
        started = time.process_time()
        refined = [smoother(est, SmootherParams()) for est in estimates]
        extra = time.process_time() - started
        scores = [
            score_walk(walk.waypoints, site.floor_index(walk), est)
            for walk, est in zip(walks, refined, strict=True)
        ]
        rows.append(summarise(f"{name} + {label}", scores, cpu_s + extra, updates))
        for walk, est in zip(walks, refined, strict=True):
            if walk.walk_id in kept:
                kept[walk.walk_id][f"{name} + {label}"] = est
    return rows


def evaluate(
    site: SiteRecordings,
    learned: Learned,
    walks: Sequence[Walk],
    methods: Sequence[str],
    *,
    keep: Iterable[str] = (),
    batched: bool = True,
    progress: Callable[[str, int], None] = lambda _m, _i: None,
) -> Evaluation:
    """Replay ``walks`` through every method; return their rows and the kept walks' estimates.

    ``batched`` runs the particle filter's walks as devices of one engine
    (the server's way, which sets its CPU per update); otherwise walk by walk.
    """
    kept: dict[str, dict[str, list[Estimate]]] = {w: {} for w in keep}
    rows: list[Row] = []
    run_s: dict[str, float] = {}
    for name in methods:
        started = time.perf_counter()
        if name in PARTICLE_FILTERS and batched:
            estimates, cpu, updates = replay_pf_batched(
                site, learned, walks, functools.partial(progress, name), name
            )
        else:
            runner = make_runner(name, learned)
            estimates, cpu, updates = [], 0.0, 0
            for i, walk in enumerate(walks):
                result = runner(site, walk)
                estimates.append(result.estimates)
                cpu += result.cpu_s
                updates += result.updates
                progress(name, i + 1)
        scores = []
        for walk, est in zip(walks, estimates, strict=True):
            scores.append(score_walk(walk.waypoints, site.floor_index(walk), est))
            if walk.walk_id in kept:
                kept[walk.walk_id][name] = est
        rows.append(summarise(name, scores, cpu, updates))
        run_s[name] = time.perf_counter() - started
        if any(e.odometry is not None for est in estimates for e in est):
            rows += smoothed_rows(site, walks, name, estimates, cpu, updates, kept)
    return Evaluation(rows, kept, run_s=run_s)
