"""Particle-filter cost per device update, batched, on a synthetic office floor.

The floor is 120 × 80 m at the service's 0.25 m raster: corridors every 20 m
and rooms with doors along them, 216 access points on a 7.5 m lattice at
3 m height with scattered path-loss parameters. Each device walks through
the plan (two 0.7 m steps per 1 s window, turning away from walls) and
hears the ``M`` strongest access points with 6 dB noise. Filters are warmed
up first, so the timed updates run in the converged regime (resampling,
mutation and centre sampling every window); the warm-up also compiles the
kernel (or loads it from numba's disk cache).

Prints the median CPU time per device update (µs) over the repeats for
1, 10, 100 and 1,000 devices per batch and 5, 20 and 50 transmitters heard,
for the filter update alone (``update_filters``, two steps per window) and
for the whole positioning loop (``PositioningEngine.process``:
preprocessing, floor selection, filter, refinement, projection; the
batches carry radio only, so particles move by the random walk). Each cell
runs the numpy reference and the compiled kernel side by side on the same
inputs, alternating update by update, so that a busy machine slows both
alike; their ratio is the speed-up.

Run: ``python -m bench.engine`` (about four minutes), ``--quick`` for fewer
updates, ``--profile`` for a cProfile of 100 devices hearing 20 transmitters
(``--kernel numpy`` for the reference's).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from typing import Any, Literal  # noqa: E402

import numpy as np  # noqa: E402

from app.core.heap import settle_heap  # noqa: E402
from app.engine.particle.bank import ParticleBank  # noqa: E402
from app.engine.particle.floor_model import build_floor_models  # noqa: E402
from app.engine.particle.inputs import FilterInput  # noqa: E402
from app.engine.particle.params import ParticleFilterParams  # noqa: E402
from app.engine.particle.update import update_filters  # noqa: E402
from app.engine.pathloss import expected_rssi, ranges_3d  # noqa: E402
from app.engine.plan import FloorPlan, burn_segments  # noqa: E402
from app.engine.positioning import PositioningEngine, PositioningParams  # noqa: E402
from app.engine.samples import Batch, RssiReadings  # noqa: E402
from app.engine.site import Emitters, Floor, SiteModel  # noqa: E402
from app.evaluation.markdown import markdown_table  # noqa: E402

WIDTH_M, HEIGHT_M, CELL_M = 120.0, 80.0, 0.25
STEP_M = 0.7
NOISE_DB = 6.0


def office_plan() -> FloorPlan:
    """Return a 120 × 80 m floor: a corridor every 20 m, 5 m rooms on both sides, doors."""
    segments = [[0, 0, WIDTH_M, 0], [WIDTH_M, 0, WIDTH_M, HEIGHT_M]]
    segments += [[WIDTH_M, HEIGHT_M, 0, HEIGHT_M], [0, HEIGHT_M, 0, 0]]
    for yc in np.arange(10.0, HEIGHT_M, 20.0):
        for side in (-1.5, 1.5):
            y = yc + side
            # corridor wall with a 1 m door every 5 m
            for x0 in np.arange(0.0, WIDTH_M, 5.0):
                segments.append([x0, y, x0 + 4.0, y])
            y_far = yc + np.sign(side) * 8.5
            segments.append([0.0, y_far, WIDTH_M, y_far])
            for x0 in np.arange(5.0, WIDTH_M, 5.0):
                segments.append([x0, y, x0, y_far])
    ny, nx = int(HEIGHT_M / CELL_M), int(WIDTH_M / CELL_M)
    free = np.ones((ny, nx), bool)
    burn_segments(free, np.array(segments, float), origin=np.zeros(2), cell=CELL_M)
    return FloorPlan.from_raster(origin=np.zeros(2), cell=CELL_M, free=free)


def office_site(rng: np.random.Generator) -> SiteModel:
    """Return the synthetic site: one office floor and its access points."""
    plan = office_plan()
    gx, gy = np.meshgrid(np.arange(3.75, WIDTH_M, 7.5), np.arange(5.0, HEIGHT_M, 7.5))
    n = gx.size
    xyz = np.column_stack([gx.ravel(), gy.ravel(), np.full(n, 3.0)])
    tx = Emitters(
        ids=tuple(f"ap{i}" for i in range(n)),
        floor=np.zeros(n, np.int32),
        xyz=xyz,
        A=rng.uniform(-45.0, -35.0, n),
        B=rng.uniform(15.0, 25.0, n),
        sigma=rng.uniform(4.0, 8.0, n),
    )
    return SiteModel("bench", (Floor("F1", 0, 4.0, plan),), tx)


class Walkers:
    """Ground truth of many devices walking the plan and the readings they take."""

    def __init__(self, site: SiteModel, d: int, rng: np.random.Generator) -> None:
        self.site = site
        self.plan = site.floors[0].plan
        self.rng = rng
        self.xy = self.plan.sample_free(d, rng)
        self.heading = rng.uniform(0.0, 360.0, d)

    def step(self) -> None:
        """Advance every walker by two steps, turning at random where a wall is ahead."""
        for _ in range(2):
            rad = np.radians(self.heading)
            new = self.xy + STEP_M * np.column_stack([np.sin(rad), np.cos(rad)])
            ok = self.plan.segment_free(self.xy, new)
            self.xy = np.where(ok[:, None], new, self.xy)
            self.heading = np.where(ok, self.heading, self.rng.uniform(0.0, 360.0, ok.size))

    def readings(self, m: int) -> tuple[np.ndarray, np.ndarray]:
        """Return (D, m) indices and RSSI (dBm) of the m strongest transmitters of each walker."""
        tx = self.site.transmitters
        r = ranges_3d(self.xy, tx.xyz, 1.2, 0.5)
        rssi = expected_rssi(r, tx.A, tx.B) + self.rng.normal(0.0, NOISE_DB, r.shape)
        top = np.argsort(-rssi, axis=1)[:, :m]
        return top, np.take_along_axis(rssi, top, axis=1)


KERNELS: tuple[Literal["numpy", "numba"], ...] = ("numpy", "numba")


def filter_inputs(
    walkers: Walkers, slots: np.ndarray, rngs: list[np.random.Generator], t: int, m: int
) -> list[FilterInput]:
    """Return one window's filter inputs: two steps and m transmitters per device."""
    tx, rssi = walkers.readings(m)
    heading = walkers.heading
    return [
        FilterInput(
            slot=int(slots[i]),
            t=t,
            tx=tx[i],
            rssi=rssi[i],
            count=np.ones(m),
            rng=rngs[i],
            step_length=np.full(2, STEP_M),
            step_heading=np.full(2, heading[i]),
        )
        for i in range(slots.size)
    ]


def time_filter(
    site: SiteModel, d: int, m: int, warmup: int, repeats: int, n: int = 1000
) -> dict[str, float]:
    """Return each kernel's median CPU µs per device of ``update_filters`` over the repeats."""
    params = ParticleFilterParams(n_particles=n)
    model = build_floor_models(site, params)[0]
    walkers = Walkers(site, d, np.random.default_rng(d * 1000 + m))
    banks = {k: ParticleBank(params.n_particles, d) for k in KERNELS}
    slots = {k: np.array([bank.allocate() for _ in range(d)]) for k, bank in banks.items()}
    rngs = {k: [np.random.default_rng(i) for i in range(d)] for k in KERNELS}
    samples: dict[str, list[float]] = {k: [] for k in KERNELS}
    for step in range(warmup + repeats):
        walkers.step()
        state = walkers.rng.bit_generator.state
        for k in KERNELS:
            # both kernels hear the same readings
            walkers.rng.bit_generator.state = state
            inputs = filter_inputs(walkers, slots[k], rngs[k], 1000 * (step + 1), m)
            start = time.process_time()
            update_filters(banks[k], model, inputs, replace(params, kernel=k))
            elapsed = time.process_time() - start
            if step >= warmup:
                samples[k].append(elapsed / d)
    return {k: float(np.median(v) * 1e6) for k, v in samples.items()}


def time_engine(
    site: SiteModel, d: int, m: int, warmup: int, repeats: int, n: int = 1000
) -> dict[str, float]:
    """Return each kernel's median CPU µs per device of ``PositioningEngine.process``."""
    engines = {
        k: PositioningEngine(
            site, PositioningParams(filter=ParticleFilterParams(n_particles=n, kernel=k))
        )
        for k in KERNELS
    }
    walkers = Walkers(site, d, np.random.default_rng(d * 1000 + m + 7))
    ids = [f"dev{i}" for i in range(d)]
    for engine in engines.values():
        for device_id in ids:
            engine.add(device_id)
    samples: dict[str, list[float]] = {k: [] for k in KERNELS}
    for step in range(warmup + repeats):
        walkers.step()
        tx, rssi = walkers.readings(m)
        t = 1000 * (step + 1) + 500
        for k, engine in engines.items():
            batches = {
                device_id: Batch(
                    rssi=RssiReadings(
                        t=np.full(m, t, np.int64), tx=tx[i].astype(np.int32), rssi=rssi[i]
                    )
                )
                for i, device_id in enumerate(ids)
            }
            start = time.process_time()
            engine.process(batches)
            elapsed = time.process_time() - start
            if step >= warmup:
                samples[k].append(elapsed / d)
    return {k: float(np.median(v) * 1e6) for k, v in samples.items()}


def main(argv: list[str] | None = None) -> None:
    """Print the tables, or a profile with ``--profile``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--kernel", choices=KERNELS, default="numba", help="kernel to profile")
    parser.add_argument("--particles", type=int, default=1000, help="N per filter")
    parser.add_argument("--devices", default="1,10,100,1000", help="batch sizes, comma-separated")
    parser.add_argument("--warmup", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--quick", action="store_true", help="3 updates to warm up, 5 timed")
    parser.add_argument("--markdown", action="store_true", help="print Markdown tables")
    args = parser.parse_args(argv)
    if args.quick:
        args.warmup, args.repeats = 3, 5
    site = office_site(np.random.default_rng(0))
    # as a worker process does once its sites are built: startup objects out of the
    # collector's passes, young collections every 50,000 new objects
    settle_heap()
    if args.profile:
        profile(site, args.kernel, args.particles)
        return
    counts = tuple(int(v) for v in args.devices.split(","))
    heard = (5, 20, 50)
    print(f"load average at start: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    for title, fn in (
        ("particle filter update (update_filters)", time_filter),
        ("whole positioning loop (PositioningEngine.process)", time_engine),
    ):
        n = args.particles
        print(f"{title}: CPU µs per device update, N = {n}, median of {args.repeats}")
        if args.markdown:
            print(markdown_rows(site, fn, counts, heard, args) + "\n")
            continue
        print(f"{'':>14s}" + "".join(f"{f'{m} tx':>24s}" for m in heard))
        print(f"{'devices/batch':>14s}" + f"{'numpy':>9s}{'numba':>8s}{'ratio':>7s}" * len(heard))
        for d in counts:
            cells = [fn(site, d, m, args.warmup, args.repeats, n) for m in heard]
            row = "".join(f"{c['numpy']:>9.0f}{c['numba']:>8.0f}{ratio(c):>7.1f}" for c in cells)
            print(f"{d:>14d}" + row)
        print()
    print(f"load average at end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


def markdown_rows(
    site: Any, fn: Any, counts: tuple[int, ...], heard: tuple[int, ...], args: Any
) -> str:
    """Return one timing table as Markdown: a numpy and a numba column per transmitter count."""
    header = ["devices per batch"] + [f"{m} tx {k}" for m in heard for k in ("numpy", "numba")]
    rows = []
    for d in counts:
        cells = [fn(site, d, m, args.warmup, args.repeats, args.particles) for m in heard]
        rows.append([d] + [f"{c[k]:.0f}" for c in cells for k in ("numpy", "numba")])
    return markdown_table(header, rows)


def ratio(cell: dict[str, float]) -> float:
    """Return the reference's time over the kernel's: the speed-up."""
    return cell["numpy"] / cell["numba"]


def profile(site: SiteModel, kernel: str, n: int) -> None:
    """Print a cProfile of one kernel's updates of 100 devices hearing 20 transmitters."""
    params = ParticleFilterParams(n_particles=n, kernel=kernel)  # type: ignore[arg-type]
    model = build_floor_models(site, params)[0]
    walkers = Walkers(site, 100, np.random.default_rng(20))
    bank = ParticleBank(n, 100)
    slots = np.array([bank.allocate() for _ in range(100)])
    rngs = [np.random.default_rng(i) for i in range(100)]
    profiler = cProfile.Profile()
    for step in range(13):
        walkers.step()
        inputs = filter_inputs(walkers, slots, rngs, 1000 * (step + 1), 20)
        # the first three updates compile (or load) the kernel and converge the filters
        if step == 3:
            profiler.enable()
        update_filters(bank, model, inputs, params)
    profiler.disable()
    pstats.Stats(profiler).sort_stats("tottime").print_stats(25)


if __name__ == "__main__":
    main()
