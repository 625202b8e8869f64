"""Measure UWB fixes, the EKF and range-bias handling on the trolley recording.

The recording is one run, so it is split by time: the first
``calibration_fraction`` is the calibration part, the rest the test part.
Truth (motion capture) of the calibration part may be used to align the two
clocks, to pick the tags' known height and to survey the range biases; every
figure is measured on the test part only. Per tag:

* ``lsq``: robust 2-D least squares of each epoch's ranges at the known
  height (input: ranges).
* ``lsq+survey``: the same after subtracting the biases surveyed on the
  calibration part (input: ranges, calibration truth).
* ``ekf``: the tag tracker (fixes → EKF, course from motion: the trolley has
  no IMU), no bias handling (input: ranges).
* ``ekf+self``: the tracker learning the biases from its own residuals from
  the start of the run (input: ranges; no truth at all).
* ``ekf+survey``: the tracker starting from the surveyed biases (input:
  ranges, calibration truth).

Run ``python -m app.evaluation.uwb_eval`` (about a minute on one core).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace

import numpy as np

from app.datasets.uwb_trolley import (
    ANCHORS_XYZ,
    N_TAGS,
    MotionCapture,
    TrolleyRanges,
    check_attitude,
    read_motion_capture,
    read_ranges,
    tag_truth,
    to_ranges,
    trolley_site,
)
from app.engine.accuracy_map import accuracy_at
from app.engine.lateration.solver import LaterationParams, solve
from app.engine.samples import Batch, Ranges
from app.engine.uwb_bias import survey_biases
from app.engine.uwb_tracker import UwbTracker, UwbTrackerParams

RANGE_STD_M = 0.1
"""Standard deviation given to every range (the recording carries none)."""

OFFSETS_MS = np.arange(-300, 301, 10)
"""Clock offsets (ms) tried when aligning ranges with motion capture."""

BATCH_MS = 1000
"""The tracker is fed batches of this much measurement time, as a gateway would send them."""


@dataclass(frozen=True)
class Errors:
    """Horizontal error statistics (m) of one method on one tag's test part."""

    n: int
    rms: float
    p95: float

    @staticmethod
    def of(err: np.ndarray) -> Errors:
        """Summarise horizontal errors (m), NaN ignored."""
        err = err[np.isfinite(err)]
        if err.size == 0:
            return Errors(0, float("nan"), float("nan"))
        # RMS = √(mean e²)
        return Errors(int(err.size), float(np.sqrt(np.mean(err**2))), float(np.quantile(err, 0.95)))


@dataclass(frozen=True)
class TagReport:
    """Everything measured for one tag."""

    tag: int
    height_m: float
    errors: dict[str, Errors]
    survey_bias: np.ndarray
    self_bias_at_split: np.ndarray
    self_bias_at_end: np.ndarray
    test_bias: np.ndarray


def raw_fixes(
    rec: TrolleyRanges, tag: int, height: float, bias: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Return (xy (N, 2), ok (N,)) of robust 2-D least squares per row, ranges minus ``bias``."""
    r = rec.ranges[:, :, tag]
    if bias is not None:
        # r̃ = r − b
        r = r - bias[None, :]
    fix = solve(
        "range",
        ANCHORS_XYZ,
        r,
        np.full(r.shape[1], RANGE_STD_M),
        height=height,
        dims=2,
        params=LaterationParams(),
    )
    return fix.position[:, :2], fix.ok


def horizontal_error(xy: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Return |xy − truth_xy| per row (m)."""
    return np.hypot(xy[:, 0] - truth[:, 0], xy[:, 1] - truth[:, 1])


def estimate_offset(
    rec: TrolleyRanges, mc: MotionCapture, part: np.ndarray, height: float
) -> tuple[int, np.ndarray]:
    """Return the clock offset (ms) minimising the raw fixes' RMS error on ``part``, and the curve.

    All tags vote together: the RMS is over the rows of every tag.
    """
    fixes = [raw_fixes(rec, tag, height) for tag in range(N_TAGS)]
    curve = np.empty(OFFSETS_MS.size)
    for i, off in enumerate(OFFSETS_MS):
        sq = []
        for tag, (xy, ok) in enumerate(fixes):
            truth = tag_truth(mc, tag, rec.t[part], float(off))
            sq.append(horizontal_error(xy[part][ok[part]], truth[ok[part]]) ** 2)
        curve[i] = np.sqrt(np.nanmean(np.concatenate(sq)))
    return int(OFFSETS_MS[int(np.nanargmin(curve))]), curve


def run_tracker(
    rec: TrolleyRanges,
    tag: int,
    params: UwbTrackerParams,
    initial_biases: np.ndarray | None = None,
    split_t: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Feed one tag's ranges to a fresh tracker in 1-s batches.

    Returns estimate times (ms), positions (M, 2), the biases it held when
    ``split_t`` was passed (or None), and its final biases.
    """
    ranges = to_ranges(rec, tag, RANGE_STD_M)
    tracker = UwbTracker(trolley_site(), params, initial_biases=initial_biases)
    t_out: list[int] = []
    xy_out: list[tuple[float, float]] = []
    at_split = None
    edges = np.arange(ranges.t[0], ranges.t[-1] + BATCH_MS, BATCH_MS)
    cut = np.searchsorted(ranges.t, edges)
    for a, b in zip(cut[:-1], cut[1:], strict=True):
        if split_t is not None and at_split is None and ranges.t[a] >= split_t:
            at_split = tracker.bias.copy()
        part = Ranges(
            t=ranges.t[a:b], anchor=ranges.anchor[a:b], range=ranges.range[a:b], std=ranges.std[a:b]
        )
        for est in tracker.process(Batch(ranges=part)):
            t_out.append(est.t)
            xy_out.append((est.x, est.y))
    return np.array(t_out, dtype=np.int64), np.array(xy_out).reshape(-1, 2), at_split, tracker.bias


def evaluate_tag(
    rec: TrolleyRanges,
    mc: MotionCapture,
    tag: int,
    calib: np.ndarray,
    offset_ms: int,
    params: UwbTrackerParams,
) -> TagReport:
    """Measure every method on one tag's test part."""
    test = ~calib
    truth = tag_truth(mc, tag, rec.t, float(offset_ms))
    height = float(np.nanmedian(truth[calib, 2]))
    params = replace(params, tag_height_m=height)
    survey = survey_biases(ANCHORS_XYZ, rec.ranges[calib, :, tag], truth[calib]).bias
    test_bias = survey_biases(ANCHORS_XYZ, rec.ranges[test, :, tag], truth[test]).bias
    errors: dict[str, Errors] = {}
    for name, bias in (("lsq", None), ("lsq+survey", survey)):
        xy, ok = raw_fixes(rec, tag, height, bias)
        errors[name] = Errors.of(horizontal_error(xy[test & ok], truth[test & ok]))
    split_t = int(rec.t[test][0])
    variants = {
        "ekf": (replace(params, self_calibrate=False), None),
        "ekf+self": (replace(params, self_calibrate=True), None),
        "ekf+survey": (replace(params, self_calibrate=False), survey),
    }
    self_split = self_end = np.full(ANCHORS_XYZ.shape[0], np.nan)
    for name, (p, init) in variants.items():
        t, xy, at_split, final = run_tracker(rec, tag, p, init, split_t)
        keep = t >= split_t
        est_truth = tag_truth(mc, tag, t[keep], float(offset_ms))
        errors[name] = Errors.of(horizontal_error(xy[keep], est_truth))
        if name == "ekf+self" and at_split is not None:
            self_split, self_end = at_split, final
    return TagReport(tag, height, errors, survey, self_split, self_end, test_bias)


def main(argv: list[str] | None = None) -> None:
    """Print the evaluation tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calibration-fraction", type=float, default=0.3)
    args = parser.parse_args(argv)

    rec = read_ranges()
    mc = read_motion_capture()
    att = check_attitude(mc)
    print(
        f"attitude: body x vs velocity offset {att.offset_deg:.1f} deg, "
        f"concentration {att.concentration:.3f}, body z up {att.up_z:.3f}, "
        f"moving {att.moving:.0%} of captures"
    )
    span = rec.t[-1] - rec.t[0]
    calib = rec.t < rec.t[0] + args.calibration_fraction * span
    print(
        f"{len(rec)} range rows over {span / 1000:.1f} s; calibration part "
        f"{calib.sum()} rows ({args.calibration_fraction:.0%}), test part {(~calib).sum()} rows"
    )
    first_truth = tag_truth(mc, 0, rec.t[calib], 0.0)
    offset, curve = estimate_offset(rec, mc, calib, float(np.nanmedian(first_truth[:, 2])))
    zero = int(np.flatnonzero(OFFSETS_MS == 0)[0])
    print(
        f"clock offset (calibration part, all tags): {offset} ms "
        f"(raw RMS {curve.min():.4f} m there vs {curve[zero]:.4f} m at 0 ms)"
    )
    centre = np.array([[0.0, 0.0, float(np.nanmedian(first_truth[:, 2]))]])
    sigma, _, dims = accuracy_at(
        centre, ANCHORS_XYZ, np.full(ANCHORS_XYZ.shape[0], RANGE_STD_M), model="range"
    )
    print(
        f"a-priori σ of one 3-D fix at the room centre (range σ {RANGE_STD_M} m): "
        f"x {sigma[0, 0]:.3f} y {sigma[0, 1]:.3f} z {sigma[0, 2]:.3f} m (dims {dims[0]}): "
        "height not meaningful, errors are horizontal"
    )
    params = UwbTrackerParams(range_std_m=RANGE_STD_M, emit_every_ms=0)
    methods = ["lsq", "lsq+survey", "ekf", "ekf+self", "ekf+survey"]
    print()
    print(
        "inputs: lsq, ekf, ekf+self = ranges only; lsq+survey, ekf+survey = ranges and "
        "biases surveyed with the calibration part's truth"
    )
    print("horizontal error on the test part, RMS / p95 (m)")
    print(f"{'tag':>4} {'z (m)':>6} " + " ".join(f"{m:>17}" for m in methods))
    reports = []
    for tag in range(N_TAGS):
        rep = evaluate_tag(rec, mc, tag, calib, offset, params)
        reports.append(rep)
        cells = " ".join(f"{rep.errors[m].rms:8.4f}/{rep.errors[m].p95:.4f}" for m in methods)
        print(f"{tag:>4} {rep.height_m:6.3f} {cells}")
    print()
    print("fixes or estimates per method on the test part")
    for rep in reports:
        print(f"tag {rep.tag}: " + ", ".join(f"{m} {rep.errors[m].n}" for m in methods))
    print()
    print("range biases per anchor (m): survey = calibration truth, test = test truth (reference)")
    for rep in reports:
        print(f"tag {rep.tag} survey   " + " ".join(f"{b:6.3f}" for b in rep.survey_bias))
        print(f"tag {rep.tag} self@split" + " ".join(f"{b:6.3f}" for b in rep.self_bias_at_split))
        print(f"tag {rep.tag} self@end " + " ".join(f"{b:6.3f}" for b in rep.self_bias_at_end))
        print(f"tag {rep.tag} test     " + " ".join(f"{b:6.3f}" for b in rep.test_bias))
        for name, b in (
            ("survey", rep.survey_bias),
            ("self@split", rep.self_bias_at_split),
            ("self@end", rep.self_bias_at_end),
        ):
            d = b - rep.test_bias
            # RMS over anchors of (estimate − test-part bias), and after removing the common part
            print(
                f"    {name:>10} vs test: RMS {np.sqrt(np.mean(d**2)):.4f} m, "
                f"without common offset {np.std(d):.4f} m"
            )


if __name__ == "__main__":
    main()
