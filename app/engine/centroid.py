"""Weighted centroid of the strongest heard transmitters.

The estimator of last resort: it needs only transmitter positions, not their
path-loss parameters, so a freshly mapped site without calibration still gets
positions. Also passes external fixes (``uwb_fix``) straight through.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from app.engine.samples import Batch, Estimate
from app.engine.site import SiteModel


@dataclass(frozen=True)
class CentroidParams:
    """Tuning of the weighted centroid."""

    window_ms: int = 2000
    """Readings this recent contribute to an estimate."""
    emit_every_ms: int = 1000
    """At most one estimate per this much measurement time while readings arrive."""
    strongest: int = 4
    """How many of the strongest transmitters are averaged."""


class WeightedCentroid:
    """Stateful weighted-centroid tracker over a site's transmitters."""

    method = "centroid"

    def __init__(
        self, site: SiteModel, params: CentroidParams, state: dict[str, Any] | None = None
    ):
        self.site = site
        self.params = params
        state = state or {}
        self.t = np.asarray(state.get("t", np.zeros(0, np.int64)), dtype=np.int64)
        self.tx = np.asarray(state.get("tx", np.zeros(0, np.int32)), dtype=np.int32)
        self.rssi = np.asarray(state.get("rssi", np.zeros(0)), dtype=float)
        self.last_emit = int(state.get("last_emit", -1))

    def snapshot(self) -> dict[str, Any]:
        """Return the recent readings and the last emission time."""
        return {"t": self.t, "tx": self.tx, "rssi": self.rssi, "last_emit": self.last_emit}

    def process(self, batch: Batch) -> list[Estimate]:
        """Emit one estimate per ``emit_every_ms`` of readings, plus every external fix."""
        out = [self._fix(batch, i) for i in range(len(batch.fixes))]
        if len(batch.rssi):
            self.t = np.concatenate([self.t, batch.rssi.t])
            self.tx = np.concatenate([self.tx, batch.rssi.tx])
            self.rssi = np.concatenate([self.rssi, batch.rssi.rssi])
            # one estimate at a reading's time once emit_every_ms has passed since the last
            for t in np.unique(batch.rssi.t):
                if self.last_emit < 0 or t - self.last_emit >= self.params.emit_every_ms:
                    estimate = self._estimate(int(t))
                    if estimate is not None:
                        out.append(estimate)
                        self.last_emit = int(t)
            keep = self.t > int(self.t.max()) - self.params.window_ms
            self.t, self.tx, self.rssi = self.t[keep], self.tx[keep], self.rssi[keep]
        out.sort(key=lambda e: e.t)
        return out

    def _fix(self, batch: Batch, i: int) -> Estimate:
        fixes = batch.fixes
        x, y, z = fixes.xyz[i]
        return Estimate(
            int(fixes.t[i]),
            float(x),
            float(y),
            float(z),
            int(fixes.floor[i]),
            float("nan"),
            float(fixes.std[i]),
            float("nan"),
            "lsq",
        )

    def _estimate(self, t: int) -> Estimate | None:
        window = (self.t <= t) & (self.t > t - self.params.window_ms)
        if not window.any():
            return None
        tx, inverse = np.unique(self.tx[window], return_inverse=True)
        # mean RSSI per transmitter over the window
        mean = np.bincount(inverse, self.rssi[window]) / np.bincount(inverse)
        order = np.argsort(-mean)[: self.params.strongest]
        tx, mean = tx[order], mean[order]
        floors = self.site.transmitters.floor[tx]
        floor = int(floors[0])
        on_floor = floors == floor
        xyz = self.site.transmitters.xyz[tx[on_floor]]
        # weights ∝ received power in milliwatts: 10^(rssi/10)
        w = 10.0 ** ((mean[on_floor] - mean[0]) / 10.0)
        w /= w.sum()
        xy = w @ xyz[:, :2]
        spread = float(np.sqrt(w @ np.sum((xyz[:, :2] - xy) ** 2, axis=1)))
        xy = self.site.floors[floor].plan.project(xy)
        return Estimate(
            t,
            float(xy[0]),
            float(xy[1]),
            0.0,
            floor,
            float("nan"),
            spread + 2.0,
            float("nan"),
            self.method,
        )
