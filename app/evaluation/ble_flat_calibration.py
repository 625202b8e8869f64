"""Calibrate the BLE flat's six anchors from its calibration recording and compare with truth.

The calibration recording is treated as a survey: every row is a scan at the
tag's LiDAR position (1.3 m above the floor) hearing some of the six anchors.
``app.engine.calibration.calibrate`` then fits, per anchor, its position and
path loss (A, B, σ) as it does for a site's surveys, with censoring (rows
where an anchor was not heard) and a soft-L1 loss. The fitted positions are
compared with ``anchors.csv``; A and B are compared with a second fit in which
the true positions are given (only A, B, σ free), and with the plain least
squares of RSSI on ln r at the true ranges that ``ble_flat_eval`` uses.

The one piece of site knowledge used is the mounting height: anchors are
fitted at the mean height of the six (a survey would know the ceiling
height, not each anchor's). Phones' sensitivity is set just below the
weakest reading in the recording.

Run ``python -m app.evaluation.ble_flat_calibration``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from app.datasets import ble_flat
from app.engine.calibration import CalibrationParams, TransmitterFit, calibrate
from app.engine.pathloss import PathLossParams, fit_pathloss, ranges_3d
from app.engine.radiomap import Survey


@dataclass(frozen=True)
class AnchorComparison:
    """One anchor: truth, the free fit, the fit at the true position, the reference fit."""

    anchor: int
    true_xyz: tuple[float, float, float]
    fitted_xy: tuple[float, float]
    position_error_m: float
    free: TransmitterFit
    known: TransmitterFit
    reference_ab: tuple[float, float, float]


def survey_of(track: ble_flat.Track) -> Survey:
    """Return the recording as located scans: one scan per row, one reading per heard anchor."""
    heard = np.isfinite(track.rssi)
    scan, tx = np.nonzero(heard)
    n = len(track)
    return Survey(
        scan_t=np.asarray(track.t, dtype=np.int64),
        scan_xy=np.asarray(track.xy, dtype=float),
        scan_floor=np.zeros(n, dtype=np.int32),
        scan_walk=np.zeros(n, dtype=np.int32),
        reading_scan=scan.astype(np.int32),
        reading_tx=tx.astype(np.int32),
        reading_rssi=track.rssi[scan, tx].astype(float),
    )


def calibration_params(anchors: ble_flat.Anchors, track: ble_flat.Track) -> CalibrationParams:
    """Return the fit's constants for the flat: tag and mount heights, sensitivity."""
    weakest = float(np.nanmin(track.rssi))
    return replace(
        CalibrationParams(),
        rx_height_m=ble_flat.TAG_HEIGHT_M,
        tx_height_m=float(np.mean(anchors.xyz[:, 2])),
        sensitivity_dbm=weakest - 1.0,
    )


def compare() -> list[AnchorComparison]:
    """Fit every anchor from the calibration recording and compare with the known anchors."""
    anchors = ble_flat.read_anchors()
    track = ble_flat.calibration()
    survey = survey_of(track)
    params = calibration_params(anchors, track)
    free = {f.tx: f for f in calibrate(survey, params)}
    truth = {i: (0, float(x), float(y), float(z)) for i, (x, y, z) in enumerate(anchors.xyz)}
    known = {f.tx: f for f in calibrate(survey, params, known=truth)}
    min_range = PathLossParams().min_range_m
    r = ranges_3d(track.xy, anchors.xyz, ble_flat.TAG_HEIGHT_M, min_range)
    out = []
    for i, anchor in enumerate(anchors.ids):
        heard = np.isfinite(track.rssi[:, i])
        ref = fit_pathloss(r[heard, i], track.rssi[heard, i], min_range)
        x, y, z = anchors.xyz[i]
        fit = free[i]
        out.append(
            AnchorComparison(
                anchor=int(anchor),
                true_xyz=(float(x), float(y), float(z)),
                fitted_xy=(fit.x, fit.y),
                position_error_m=float(np.hypot(fit.x - x, fit.y - y)),
                free=fit,
                known=known[i],
                reference_ab=(float(ref[0]), float(ref[1]), float(ref[2])),
            )
        )
    return out


def main() -> None:
    """Print the per-anchor comparison table and the mean position error."""
    rows = compare()
    print(
        f"{'anchor':>6s} {'true x':>7s} {'true y':>7s} {'fit x':>7s} {'fit y':>7s} "
        f"{'err m':>6s} | {'A':>7s} {'B':>6s} {'σ':>5s} | {'A@true':>7s} {'B@true':>6s} "
        f"{'σ@true':>6s} | {'A ref':>7s} {'B ref':>6s} {'σ ref':>5s} | {'n':>5s} {'plaus':>5s}"
    )
    for c in rows:
        f, k, (ra, rb, rs) = c.free, c.known, c.reference_ab
        print(
            f"{c.anchor:6d} {c.true_xyz[0]:7.2f} {c.true_xyz[1]:7.2f} {f.x:7.2f} {f.y:7.2f} "
            f"{c.position_error_m:6.2f} | {f.A:7.2f} {f.B:6.2f} {f.sigma:5.2f} | "
            f"{k.A:7.2f} {k.B:6.2f} {k.sigma:6.2f} | {ra:7.2f} {rb:6.2f} {rs:5.2f} | "
            f"{f.n_readings:5d} {str(f.plausible):>5s}"
        )
    errors = np.array([c.position_error_m for c in rows])
    print(
        f"position error: mean {errors.mean():.2f} m, median {np.median(errors):.2f} m, "
        f"max {errors.max():.2f} m"
    )


if __name__ == "__main__":
    main()
