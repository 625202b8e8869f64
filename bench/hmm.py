"""The phone tracker's (HMM) cost per device update on ILC site1's held-out walks.

Radio maps are built from the training walks of the walk split (as a
radio-map build does), then ``--walks`` test walks are replayed through
``HmmTracker`` in one-second batches, as phones upload them. Prints the
CPU time per device update (median, mean, p95), the per-scan cost of the
survey-scan distance and of the whole emission, the live fixed-lag
smoother's time per update (its refined positions, as a worker adds them),
and the maps' size.

Run: ``python -m bench.hmm`` (about two minutes, most of it reading site1
and building its maps); ``--site`` names another ILC site folder.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from app.datasets import data_dir  # noqa: E402
from app.datasets.ilc import site_walks  # noqa: E402
from app.engine.hmm.emission import EmissionModel  # noqa: E402
from app.engine.hmm.kernels import load_kernels  # noqa: E402
from app.engine.hmm.params import HmmParams  # noqa: E402
from app.engine.hmm.tracker import HmmTracker  # noqa: E402
from app.engine.pdr import PdrParams  # noqa: E402
from app.engine.pdr_kernel import load_kernel as load_pdr_kernel  # noqa: E402
from app.engine.radiomap import RadioMapParams  # noqa: E402
from app.engine.scans import load_grouping  # noqa: E402
from app.engine.smoothing import (  # noqa: E402
    FixedLagSmoother,
    SmootherParams,
    load_solver,
)
from app.engine.wknn import unique_readings  # noqa: E402
from app.evaluation.ilc.learn import radio_maps  # noqa: E402
from app.evaluation.ilc.recordings import (  # noqa: E402
    read_site_recordings,
    survey_of,
    walk_batches,
)
from app.evaluation.split import split_ids  # noqa: E402


def per_call_ms(
    calls: list[tuple[np.ndarray, np.ndarray]], fn: Callable[[np.ndarray, np.ndarray], object]
) -> np.ndarray:
    """Return the wall time (ms) of ``fn(tx, rssi)`` on each scan."""
    out = []
    for tx, rssi in calls:
        t0 = time.perf_counter()
        fn(tx, rssi)
        out.append(time.perf_counter() - t0)
    return 1e3 * np.array(out)


def main(argv: list[str] | None = None) -> None:
    """Build site1's maps from its training walks and time the HMM on test walks."""
    parser = argparse.ArgumentParser(prog="python -m bench.hmm", description=__doc__)
    parser.add_argument("--site", type=Path, default=None, help="default: <data>/ilc/site1")
    parser.add_argument("--walks", type=int, default=20, help="test walks replayed")
    args = parser.parse_args(argv)
    console = Console()
    site_dir = args.site or data_dir() / "ilc" / "site1"
    ids = [path.name.split(".")[0] for _, path in site_walks(site_dir)]
    train, _, test = split_ids(ids, 0.2, 0.0)
    with console.status("reading the site and building its radio maps"):
        site = read_site_recordings(site_dir, train_ids=train)
        maps = radio_maps(site, survey_of(site, set(train)), RadioMapParams())
        t0 = time.perf_counter()
        model = EmissionModel(maps, HmmParams())
        prepare_s = time.perf_counter() - t0
    chosen = set(test)
    walks = sorted(
        (w for w in site.walks if w.walk_id in chosen and w.waypoints.shape[0] >= 2),
        key=lambda w: w.walk_id,
    )[: args.walks]
    batches = [list(walk_batches(site, w)) for w in walks]
    scans = [
        unique_readings(b.rssi.tx, b.rssi.rssi) for walk in batches for b in walk if b.rssi.t.size
    ]
    assert model.references is not None
    refs = model.references
    # the first call compiles (or loads the compiled kernel from its disk cache)
    refs.distances(*scans[0])
    model.log_likelihoods(*scans[0])
    distance_ms = per_call_ms(scans, refs.distances)

    def emission(tx: np.ndarray, rssi: np.ndarray) -> None:
        # time the whole emission, not the cached distances and evidence
        model._cache, model._evidence = None, None
        model.log_likelihoods(tx, rssi)

    emission_ms = per_call_ms(scans, emission)
    lag = SmootherParams()
    # compiled once per process, as a worker warms a site
    refs.level_offset(*scans[0], np.zeros(1, dtype=np.int64))
    load_kernels()
    load_pdr_kernel()
    load_grouping()
    load_solver()
    # and whatever else the tracker compiles on its first scans: one walk, untimed
    warm = HmmTracker(model, HmmParams(), PdrParams())
    for batch in batches[0]:
        warm.process(batch)
    update_ms, smoother_ms = [], []
    for walk in batches:
        tracker = HmmTracker(model, HmmParams(), PdrParams())
        smoother = FixedLagSmoother(lag)
        for batch in walk:
            t0 = time.process_time()
            estimates = tracker.process(batch)
            t1 = time.process_time()
            smoother.push(estimates)
            update_ms.append(1e3 * (t1 - t0))
            smoother_ms.append(1e3 * (time.process_time() - t1))
    updates = np.array(update_ms)

    table = Table(title=f"HMM on {site_dir.name}: {len(walks)} test walks, {updates.size} updates")
    for col in ("measure", "median", "mean", "p95", "n"):
        table.add_column(col, justify="right" if col != "measure" else "left")
    for name, v in (
        ("CPU per device update (ms)", updates),
        ("fixed-lag smoother per device update (ms)", np.array(smoother_ms)),
        ("survey-scan distances per scan (ms)", distance_ms),
        ("emission per scan (ms)", emission_ms),
    ):
        table.add_row(
            name,
            f"{np.median(v):.3f}",
            f"{v.mean():.3f}",
            f"{np.percentile(v, 95):.3f}",
            str(v.size),
        )
    console.print(table)
    console.print(
        f"{refs.n_scans} reference scans holding {refs.ref_scan.size} (scan, transmitter) "
        f"pairs; {sum(m.n_points for m in maps)} map points; the site's emission "
        f"prepared in {prepare_s:.1f} s"
    )


if __name__ == "__main__":
    main()
