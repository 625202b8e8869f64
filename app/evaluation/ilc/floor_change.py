"""How fast the particle filter's floor follows a device that changes floor, on ILC site1.

Every ILC walk stays on one floor, so a change of floor is built: walk A is
replayed, then walk B of another floor with its times shifted to start one
window after A's end, as one device. Both walks are held out (validation or
test, as ``locus eval ilc`` splits them); everything is learned from the
training walks. B is paired to A as the next walk in id order on another
floor, so every held-out walk is an A once.

The change is abrupt: a real one passes through stairs, an escalator or a
lift, where readings of both floors mix for a while, and a barometer (ILC
recorded none) would show the climb. Reported per method: seconds from the
change to the first estimate on B's floor ("first"), to the first estimate
on it that no estimate off it follows ("settled"), and from B's first WiFi
scan to the first estimate on B's floor ("after scan"); the share of
estimates on a wrong floor before the change; and the share off B's floor
after the first estimate on it (flicker back).

Run ``locus eval ilc-floor-change`` or ``python -m app.evaluation.ilc.floor_change``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from app.datasets.ilc import Walk
from app.engine.samples import Batch, Estimate
from app.evaluation.ilc.experiment import add_split_arguments, prepare_experiment
from app.evaluation.ilc.learn import Learned, remap
from app.evaluation.ilc.methods import PARTICLE_FILTERS, pf_engine
from app.evaluation.ilc.recordings import SiteRecordings, walk_batches
from app.evaluation.ilc.replay import replay_devices

WINDOW_MS = 1000
"""Batch length (ms) of the replay, the engine's positioning window."""


def shifted(batch: Batch, shift_ms: int) -> Batch:
    """Return the batch with its RSSI and inertial times moved by ``shift_ms``."""
    return replace(
        batch,
        rssi=replace(batch.rssi, t=batch.rssi.t + shift_ms),
        imu=replace(batch.imu, t=batch.imu.t + shift_ms),
    )


def pair_walks(walks: Sequence[Walk]) -> list[tuple[Walk, Walk]]:
    """Pair each walk with the next one (in id order, cyclically) on another floor."""
    ordered = sorted(walks, key=lambda w: w.walk_id)
    pairs = []
    for i, a in enumerate(ordered):
        b = next((w for w in ordered[i + 1 :] + ordered[:i] if w.floor != a.floor), None)
        if b is not None:
            pairs.append((a, b))
    return pairs


@dataclass(frozen=True)
class Joined:
    """Two walks replayed as one device: batches, the change time (ms) and B's first scan (ms)."""

    device_id: str
    batches: list[Batch]
    change_t: int
    first_scan_t: int
    floor_a: int
    floor_b: int


def join(site: SiteRecordings, a: Walk, b: Walk) -> Joined:
    """Concatenate the batches of ``a`` and ``b``, B shifted to start one window after A ends."""
    first = list(walk_batches(site, a, WINDOW_MS))
    second = list(walk_batches(site, b, WINDOW_MS))
    end_a = max(int(x.rssi.t.max(initial=0)) for x in first)
    end_a = max(end_a, max(int(x.imu.t.max(initial=0)) for x in first))
    start_b = min(int(min(x.rssi.t.min(initial=2**62), x.imu.t.min(initial=2**62))) for x in second)
    # B starts at the window after A's last sample, on the window grid
    change = (end_a // WINDOW_MS + 1) * WINDOW_MS
    shift = change - start_b
    moved = [shifted(x, shift) for x in second]
    scans = [int(x.rssi.t.min()) for x in moved if len(x.rssi)]
    return Joined(
        device_id=f"{a.walk_id}+{b.walk_id}",
        batches=first + moved,
        change_t=change,
        first_scan_t=scans[0] if scans else change,
        floor_a=site.floor_index(a),
        floor_b=site.floor_index(b),
    )


def replay_joined(
    learned: Learned, joined: Sequence[Joined], name: str
) -> dict[str, list[Estimate]]:
    """Replay the joined walks as devices of one engine; return each device's estimates."""
    result = replay_devices(
        pf_engine(name, learned),
        {j.device_id: iter(j.batches) for j in joined},
        transform=lambda b: remap(b, learned.pf_lookup),
    )
    return result.estimates


@dataclass(frozen=True)
class Latency:
    """One joined device's floor switch: seconds after the change, and wrong-floor counts."""

    first_s: float
    settled_s: float
    after_scan_s: float
    wrong_before: int
    n_before: int
    wrong_after: int
    n_after: int
    """Estimates off B's floor after the first one on it, and estimates after that one."""


def latency(j: Joined, estimates: Sequence[Estimate]) -> Latency:
    """Measure when the estimates reach and stay on B's floor (inf when they never do)."""
    t = np.array([e.t for e in estimates], dtype=np.int64)
    floor = np.array([e.floor for e in estimates], dtype=np.int64)
    before, after = t < j.change_t, t >= j.change_t
    on_b = after & (floor == j.floor_b)
    first = float((t[on_b][0] - j.change_t) / 1000.0) if on_b.any() else float("inf")
    off_b = after & (floor != j.floor_b)
    # settled: the first estimate on B's floor after the last one off it
    stays = on_b & (t > t[off_b].max()) if off_b.any() else on_b
    settled = float((t[stays][0] - j.change_t) / 1000.0) if stays.any() else float("inf")
    after_scan = first - (j.first_scan_t - j.change_t) / 1000.0
    # back off B's floor once there: flicker
    since = after & (t > (t[on_b][0] if on_b.any() else np.iinfo(np.int64).max))
    return Latency(
        first_s=first,
        settled_s=settled,
        after_scan_s=after_scan,
        wrong_before=int((floor[before] != j.floor_a).sum()),
        n_before=int(before.sum()),
        wrong_after=int((floor[since] != j.floor_b).sum()),
        n_after=int(since.sum()),
    )


def describe(values: np.ndarray) -> str:
    """Return median, 90th percentile and maximum of finite values, and how many are not."""
    finite = values[np.isfinite(values)]
    never = int((~np.isfinite(values)).sum())
    if finite.size == 0:
        return f"never ({never})"
    text = (
        f"median {np.median(finite):.1f} s, p90 {np.percentile(finite, 90):.1f} s, "
        f"max {finite.max():.1f} s"
    )
    return text + (f", never {never}" if never else "")


def main(argv: Sequence[str] | None = None) -> None:
    """Learn on the training walks, replay joined held-out walks and print the switch latency."""
    parser = argparse.ArgumentParser(
        prog="locus eval ilc-floor-change",
        description=__doc__.splitlines()[0] if __doc__ else None,
    )
    add_split_arguments(parser, "join its walks instead of the test walks")
    parser.add_argument("--limit", type=int, help="at most this many pairs")
    parser.add_argument(
        "--methods", nargs="+", default=list(PARTICLE_FILTERS), choices=PARTICLE_FILTERS
    )
    args = parser.parse_args(argv)
    exp = prepare_experiment(args)
    pairs = pair_walks(exp.held_out_walks())[: args.limit]
    joined = [join(exp.site, a, b) for a, b in pairs]
    print(f"site1: {len(pairs)} pairs of held-out {exp.held_out_kind} walks on different floors")
    for name in args.methods:
        estimates = replay_joined(exp.learned, joined, name)
        lat = [latency(j, estimates[j.device_id]) for j in joined]
        first = np.array([x.first_s for x in lat])
        settled = np.array([x.settled_s for x in lat])
        after_scan = np.array([x.after_scan_s for x in lat])
        wb, nb = sum(x.wrong_before for x in lat), sum(x.n_before for x in lat)
        wa, na = sum(x.wrong_after for x in lat), sum(x.n_after for x in lat)
        print(f"{name}:")
        print(f"  first estimate on the new floor after the change: {describe(first)}")
        print(f"  settled on the new floor after the change:        {describe(settled)}")
        print(f"  first estimate on the new floor after its first scan: {describe(after_scan)}")
        print(
            f"  wrong floor before the change {100.0 * wb / max(nb, 1):.2f}% of {nb}; "
            f"back off the new floor once on it {100.0 * wa / max(na, 1):.2f}% of {na}"
        )


if __name__ == "__main__":
    main()
