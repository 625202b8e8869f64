"""The particle filter replayed as devices of one engine gives each walk's own estimates."""

from __future__ import annotations

from dataclasses import astuple
from pathlib import Path

import numpy as np

from app.datasets.ilc import Walk, WifiScan
from app.engine.calibration import TransmitterFit
from app.engine.pdr import PdrParams
from app.engine.plan import FloorPlan
from app.engine.tuning import SiteTuning
from app.evaluation.ilc.learn import Learned, pf_site_model
from app.evaluation.ilc.methods import make_runner, replay_pf_batched
from app.evaluation.ilc.recordings import SiteRecordings, walk_batches
from app.evaluation.ilc.score import score_walk


def _synthetic_walk(walk_id: str, heard: int, rng: np.random.Generator) -> Walk:
    """A 12 s walk east along y = 5 at 1 m/s, one scan a second of the first ``heard`` APs."""
    t_scan = np.arange(12) * 1000 + 500
    x = 2.0 + t_scan / 1000.0
    r = np.hypot(x[:, None] - AP_XY[None, :heard, 0], 5.0 - AP_XY[None, :heard, 1])
    rssi = -40.0 - 15.0 * np.log(np.hypot(r, 1.8)) + rng.normal(0, 3, r.shape)
    t = np.repeat(t_scan, heard)
    empty = np.zeros((0, 4))
    return Walk(
        walk_id=walk_id,
        floor="F1",
        path=Path(walk_id),
        acc=empty,
        gyro=empty,
        mag=empty,
        rot=empty,
        wifi=WifiScan(
            t=t,
            bssid=np.tile(np.array(AP_IDS[:heard]), t_scan.size),
            rssi=rssi.ravel(),
            freq=np.full(t.size, 2437.0),
            last_seen=t.copy(),
        ),
        beacons=None,  # type: ignore[arg-type]
        waypoints=np.array([[0, 1.5, 5.0], [13_000, 14.5, 5.0]]),
    )


AP_IDS = ("ap0", "ap1", "ap2", "ap3", "ap4")
AP_XY = np.array([[2.0, 2.0], [18.0, 2.0], [18.0, 8.0], [2.0, 8.0], [10.0, 5.0]])


def test_batched_particle_filter_replay_equals_walk_by_walk() -> None:
    # Walks hearing 3, 4 and 5 APs widen the batch's readings table differently:
    # each walk's estimates must be those of replaying it alone.
    rng = np.random.default_rng(8)
    plan = FloorPlan.from_raster(origin=np.zeros(2), cell=0.5, free=np.ones((20, 40), bool))
    walks = tuple(_synthetic_walk(f"w{k}", k, rng) for k in (3, 5, 4))
    site = SiteRecordings(floors=("F1",), plans=(plan,), walks=walks, tx_ids=AP_IDS)
    fits = [
        TransmitterFit(i, 0, *AP_XY[i], 3.0, -40.0, 15.0, 4.0, 50, 0, 5.0, True, True, False)
        for i in range(len(AP_IDS))
    ]
    model, lookup = pf_site_model(site, fits)
    learned = Learned((), tuple(fits), PdrParams(), model, lookup, SiteTuning.defaults())
    batched, _, updates = replay_pf_batched(site, learned, walks)
    assert updates == sum(len(list(walk_batches(site, w))) for w in walks)
    alone = make_runner("pf", learned)
    for walk, got in zip(walks, batched, strict=True):
        expected = alone(site, walk).estimates
        assert len(got) == len(expected) > 5
        np.testing.assert_array_equal(
            np.array([astuple(e)[:8] for e in got], float),
            np.array([astuple(e)[:8] for e in expected], float),
        )
        # and the filter does track the walk
        assert score_walk(walk.waypoints, 0, got).error[-3:].max() < 4.0
