"""The particle filter's transmitter table and the batches mapped into it."""

from __future__ import annotations

import numpy as np

from app.engine.calibration import TransmitterFit
from app.engine.plan import FloorPlan
from app.engine.samples import Batch, RssiReadings
from app.evaluation.ilc.learn import pf_site_model, remap
from app.evaluation.ilc.recordings import SiteRecordings


def test_remap_drops_transmitters_unknown_to_the_filter() -> None:
    batch = Batch(
        rssi=RssiReadings(
            t=np.array([1, 1, 2], np.int64),
            tx=np.array([0, 1, 2], np.int32),
            rssi=np.array([-50.0, -60.0, -70.0]),
        )
    )
    out = remap(batch, np.array([-1, 0, 5]))
    assert out.rssi.tx.tolist() == [0, 5]
    assert out.rssi.rssi.tolist() == [-60.0, -70.0]
    assert out.rssi.t.tolist() == [1, 2]


def _fit(tx: int, floor: int, plausible: bool) -> TransmitterFit:
    return TransmitterFit(
        tx, floor, 1.0 * tx, 2.0, 3.0, -40.0, 15.0, 5.0, 20, 3, 4.0, True, plausible, False
    )


def test_pf_site_keeps_plausible_fits_and_maps_the_site_indices_to_them() -> None:
    plan = FloorPlan.from_raster(origin=np.zeros(2), cell=1.0, free=np.ones((4, 4), bool))
    site = SiteRecordings(
        floors=("B1", "F1"), plans=(plan, plan), walks=(), tx_ids=("a", "b", "c", "d")
    )
    model, lookup = pf_site_model(site, [_fit(0, 1, True), _fit(2, 0, False), _fit(3, 0, True)])
    assert lookup.tolist() == [0, -1, -1, 1]
    assert model.transmitters.ids == ("a", "d")
    assert model.transmitters.floor.tolist() == [1, 0]
    assert model.transmitters.xyz[1].tolist() == [3.0, 2.0, 3.0]
    assert [f.level for f in model.floors] == [-1, 0]
