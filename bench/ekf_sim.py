"""Brovko's claim in simulation: RMS of the UWB + inertial EKF against the raw fixes.

A walker at 1.2 m/s turns at a random constant rate (±0.4 rad/s) for 5 s at a
time, for 120 s. UWB fixes arrive at 10 Hz with σ = 0.3 m per axis; the gyro
gives the yaw rate at 50 Hz with a 0.01 rad/s bias and 0.02 rad/s noise. The
EKF (state [x, y, V, α]) runs once with the gyro and once with the course from
motion alone. Prints, per seed and as the median over seeds, the RMS of the
fixes, of each filter (after a 5 s settling time) and their ratios.

    python -m bench.ekf_sim --seeds 10
"""

from __future__ import annotations

import argparse

import numpy as np

from app.engine.ekf import EkfParams
from app.engine.plan import FloorPlan
from app.engine.samples import Batch, Fixes, ImuSamples
from app.engine.site import Floor, SiteModel
from app.engine.uwb_tracker import UwbTracker, UwbTrackerParams

T0 = 1_700_000_000_000
FIX_STD_M = 0.3
FIX_EVERY = 5
"""One fix per this many 50 Hz IMU samples: 10 Hz."""


def walk(rng: np.random.Generator, seconds: float = 120.0, dt: float = 0.02):
    """Return times (ms), positions (n, 2) and yaw rates (rad/s) of a turning walk."""
    n = int(seconds / dt)
    t = np.arange(n) * dt
    rate = np.repeat(rng.uniform(-0.4, 0.4, n // 250 + 1), 250)[:n]
    course = np.cumsum(rate) * dt
    v = 1.2 + 0.1 * np.sin(0.3 * t)
    xy = np.column_stack([np.cumsum(v * np.cos(course)), np.cumsum(v * np.sin(course))]) * dt
    return (T0 + np.round(t * 1000)).astype(np.int64), xy, rate


def run(seed: int) -> tuple[float, float, float]:
    """Return the RMS (m) of the fixes, the EKF with gyro and the EKF without, for one walk."""
    rng = np.random.default_rng(seed)
    t, xy, rate = walk(rng)
    idx = np.arange(0, t.size, FIX_EVERY)
    noisy = xy[idx] + rng.normal(0.0, FIX_STD_M, (idx.size, 2))
    fixes = Fixes(
        t=t[idx],
        xyz=np.column_stack([noisy, np.ones(idx.size)]),
        floor=np.zeros(idx.size, np.int32),
        std=np.full(idx.size, FIX_STD_M),
    )
    imu = ImuSamples(
        t=t,
        acc=np.tile([0.0, 0.0, 9.81], (t.size, 1)),
        gyro=np.column_stack([np.zeros((t.size, 2)), rate + 0.01 + rng.normal(0, 0.02, t.size)]),
        mag=np.full((t.size, 3), np.nan),
        rot=np.full((t.size, 4), np.nan),
    )
    plan = FloorPlan.from_raster(
        origin=np.array([-500.0, -500.0]), cell=1.0, free=np.ones((1000, 1000), bool)
    )
    site = SiteModel("sim", (Floor("F", 0, 4.0, plan),))
    params = UwbTrackerParams(
        ekf=EkfParams(accel_noise=0.05, turn_noise_gyro=0.02, position_noise=0.0), emit_every_ms=0
    )
    raw = float(np.sqrt(np.mean(np.sum((noisy - xy[idx]) ** 2, axis=1))))
    out = []
    for with_gyro in (True, False):
        tracker = UwbTracker(site, params)
        estimates = []
        for lo in range(int(t[0]), int(t[-1]) + 1000, 1000):
            f = (fixes.t >= lo) & (fixes.t < lo + 1000)
            i = (imu.t >= lo) & (imu.t < lo + 1000)
            batch = Batch(
                fixes=Fixes(t=fixes.t[f], xyz=fixes.xyz[f], floor=fixes.floor[f], std=fixes.std[f]),
                imu=ImuSamples(t=imu.t[i], acc=imu.acc[i], gyro=imu.gyro[i], mag=imu.mag[i],
                               rot=imu.rot[i]) if with_gyro else ImuSamples(),
            )  # fmt: skip
            estimates += tracker.process(batch)
        et = np.array([e.t for e in estimates])
        est = np.array([[e.x, e.y] for e in estimates])
        truth = np.column_stack([np.interp(et, t, xy[:, 0]), np.interp(et, t, xy[:, 1])])
        settled = et > T0 + 5000
        out.append(float(np.sqrt(np.mean(np.sum((est - truth)[settled] ** 2, axis=1)))))
    return raw, out[0], out[1]


def main() -> None:
    """Print the table over seeds."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    args = parser.parse_args()
    rows = np.array([run(seed) for seed in range(args.seeds)])
    print(
        f"{'seed':>6} {'fixes RMS':>10} {'EKF+gyro':>9} {'ratio':>6} {'EKF only':>9} {'ratio':>6}"
    )
    for seed, (raw, gyro, motion) in enumerate(rows):
        print(
            f"{seed:>6} {raw:>10.3f} {gyro:>9.3f} {gyro / raw:>6.3f} {motion:>9.3f} "
            f"{motion / raw:>6.3f}"
        )
    raw, gyro, motion = np.median(rows, axis=0)
    ratio_g = np.median(rows[:, 1] / rows[:, 0])
    ratio_m = np.median(rows[:, 2] / rows[:, 0])
    print(f"{'median':>6} {raw:>10.3f} {gyro:>9.3f} {ratio_g:>6.3f} {motion:>9.3f} {ratio_m:>6.3f}")


if __name__ == "__main__":
    main()
