"""A site assembled from the database for the engine: its SiteModel plus the id maps and
zones around it, as the workers, radio-map builds and planning read it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry.base import BaseGeometry
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.engine.radiomap import RadioMap
from app.engine.site import Emitters, Floor, SiteModel
from app.engine.tuning import SiteTuning
from app.floors.service import list_floors
from app.geometry.floormap import Emitter, parse_floor_map
from app.geometry.raster import floor_plan
from app.radiomaps.codec import decode_map
from app.radiomaps.models import CalibratedTransmitter, RadioMapBuild, RadioMapFloor
from app.sites.models import Site

SURVEYED_TX_HEIGHT_M = 3.0
"""Height (m) given to a transmitter known only from the radio map (no fit): the
calibration's nominal ceiling mount."""


@dataclass(frozen=True, eq=False)
class Zone:
    """A named geofence on one floor."""

    name: str
    floor: int
    polygon: BaseGeometry
    bounds: tuple[float, float, float, float] = field(init=False)
    """The polygon's (min x, min y, max x, max y)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "bounds", tuple(self.polygon.bounds))

    def contains(self, x: float, y: float) -> bool:
        """Return whether (x, y) lies inside the zone (not on its edge).

        The bounding box is compared first: most positions lie outside most
        zones, and the comparison is far cheaper than shapely's call.
        """
        x0, y0, x1, y1 = self.bounds
        return x0 <= x <= x1 and y0 <= y <= y1 and bool(shapely.contains_xy(self.polygon, x, y))

    def near(self, x: float, y: float, radius: float) -> bool:
        """Return whether (x, y) lies within ``radius`` (m) of the zone."""
        x0, y0, x1, y1 = self.bounds
        if not (x0 - radius <= x <= x1 + radius and y0 - radius <= y <= y1 + radius):
            return False
        return bool(shapely.dwithin(self.polygon, shapely.Point(x, y), radius))


@dataclass(frozen=True, eq=False)
class LoadedSite:
    """Everything a worker needs to turn a site's samples into positions."""

    site_id: str
    version: int
    model: SiteModel
    floor_ids: tuple[str, ...]
    floor_index: dict[str, int]
    transmitter_index: dict[str, int]
    anchor_index: dict[str, int]
    locator_index: dict[str, int]
    zones: tuple[Zone, ...]
    engine: str = "hmm"
    radio_maps: tuple[RadioMap, ...] = ()
    tuning: SiteTuning = field(default_factory=SiteTuning.defaults)

    def has_pathloss(self) -> bool:
        """Return whether any transmitter has a complete path-loss model."""
        tx = self.model.transmitters
        return bool(len(tx)) and bool(np.isfinite(tx.A + tx.B + tx.sigma).any())


def site_tuning(db: Session, site_id: str) -> SiteTuning:
    """Return the constants the site's latest radio-map build chose (defaults without one).

    A build stored before builds chose constants still gives its held-out
    median error as the accuracy floor.
    """
    build = db.get(RadioMapBuild, site_id)
    summary = (build.summary or {}) if build is not None else {}
    if summary.get("tuning"):
        return SiteTuning.from_dict(summary["tuning"])
    p50 = (summary.get("accuracy") or {}).get("p50_error_m")
    return SiteTuning.from_dict({"accuracy_floor_m": p50} if p50 is not None else None)


def _emitters(rows: list[tuple[int, Emitter]]) -> Emitters:
    def num(v: float | None) -> float:
        return float("nan") if v is None else v

    return Emitters(
        ids=tuple(e.id for _, e in rows),
        floor=np.array([f for f, _ in rows], dtype=np.int32),
        xyz=np.array([[e.x, e.y, e.z] for _, e in rows], dtype=float).reshape(-1, 3),
        A=np.array([num(e.A) for _, e in rows], dtype=float),
        B=np.array([num(e.B) for _, e in rows], dtype=float),
        sigma=np.array([num(e.sigma) for _, e in rows], dtype=float),
    )


def _with_radiomap(
    db: Session, site_id: str, table: Emitters, floor_index: dict[str, int]
) -> tuple[Emitters, tuple[RadioMap, ...]]:
    """Return the transmitter table completed by the site's build, and its radio maps.

    Map transmitters keep what the map says; where it lacks A, B or sigma, a
    plausible fit fills them. Transmitters the map does not have are appended:
    fitted ones with their fitted floor and position (path loss only when the
    fit is plausible), the others (in a radio map but too rarely heard to fit)
    at the reference point where they are strongest, without path loss. Radio
    map columns are renumbered into this table.
    """
    fits = db.scalars(
        select(CalibratedTransmitter)
        .where(CalibratedTransmitter.site_id == site_id)
        .order_by(CalibratedTransmitter.transmitter_id)
    ).all()
    rows = db.scalars(
        select(RadioMapFloor)
        .where(RadioMapFloor.site_id == site_id)
        .order_by(RadioMapFloor.floor_id)
    ).all()
    if not fits and not rows:
        return table, ()
    ids = list(table.ids)
    index = {tx: i for i, tx in enumerate(ids)}
    floor = list(table.floor)
    xyz = [tuple(v) for v in table.xyz]
    A, B, sigma = list(table.A), list(table.B), list(table.sigma)

    def add(tx: str, f: int, pos: tuple[float, float, float]) -> int:
        index[tx] = len(ids)
        ids.append(tx)
        floor.append(f)
        xyz.append(pos)
        A.append(np.nan)
        B.append(np.nan)
        sigma.append(np.nan)
        return index[tx]

    for fit in fits:
        if fit.floor_id not in floor_index:
            continue
        i = index.get(fit.transmitter_id)
        if i is None:
            i = add(fit.transmitter_id, floor_index[fit.floor_id], (fit.x, fit.y, fit.z))
        if fit.plausible and not np.isfinite(A[i] + B[i] + sigma[i]):
            A[i], B[i], sigma[i] = fit.A, fit.B, fit.sigma
    maps = []
    for row in rows:
        if row.floor_id not in floor_index:
            continue
        m = decode_map(row.data)
        f = floor_index[row.floor_id]
        columns = np.empty(len(row.transmitters), dtype=np.int32)
        for c, tx in enumerate(row.transmitters):
            if tx not in index:
                # strongest reference point: argmax of the column's mean RSSI
                p = int(np.nanargmax(np.where(np.isfinite(m.mean[:, c]), m.mean[:, c], -np.inf)))
                x, y = m.xy[p]
                add(tx, f, (float(x), float(y), SURVEYED_TX_HEIGHT_M))
            columns[c] = index[tx]
        maps.append(
            RadioMap(
                floor=f,
                cell=m.cell,
                origin=m.origin,
                shape=m.shape,
                ij=m.ij,
                tx=columns,
                mean=m.mean,
                var=m.var,
                detect=m.detect,
                weight=m.weight,
                references=m.references,
            )
        )
    completed = Emitters(
        ids=tuple(ids),
        floor=np.array(floor, dtype=np.int32),
        xyz=np.array(xyz, dtype=float).reshape(-1, 3),
        A=np.array(A, dtype=float),
        B=np.array(B, dtype=float),
        sigma=np.array(sigma, dtype=float),
    )
    return completed, tuple(sorted(maps, key=lambda m: m.floor))


def assemble_site(
    *, db: Session, site: Site, raster_cell: float, with_radiomap: bool = True
) -> LoadedSite:
    """Assemble the site's engine view from its stored floors and (unless told not to) its
    latest radio-map build."""
    floors: list[Floor] = []
    zones: list[Zone] = []
    emitters: dict[str, list[tuple[int, Emitter]]] = {
        "transmitter": [],
        "anchor": [],
        "locator": [],
    }
    z0 = 0.0
    rows = list_floors(db=db, site_id=site.id)
    # z of each floor surface: levels stacked by their heights from the lowest floor
    for index, row in enumerate(rows):
        fmap = parse_floor_map(row.geojson)
        floors.append(
            Floor(row.floor_id, row.level, row.height, floor_plan(fmap, cell=raster_cell), z0)
        )
        z0 += row.height
        for name, polygon in fmap.zones:
            shapely.prepare(polygon)
            zones.append(Zone(name, index, polygon))
        for emitter in fmap.emitters:
            emitters[emitter.kind].append((index, emitter))
    tables = {kind: _emitters(items) for kind, items in emitters.items()}
    floor_index = {f.floor_id: i for i, f in enumerate(floors)}
    radio_maps: tuple[RadioMap, ...] = ()
    tuning = SiteTuning.defaults()
    if with_radiomap:
        tables["transmitter"], radio_maps = _with_radiomap(
            db, site.id, tables["transmitter"], floor_index
        )
        tuning = site_tuning(db, site.id) if radio_maps else tuning
    model = SiteModel(
        site_id=site.id,
        floors=tuple(floors),
        transmitters=tables["transmitter"],
        anchors=tables["anchor"],
        locators=tables["locator"],
    )
    return LoadedSite(
        site_id=site.id,
        version=site.map_version,
        model=model,
        floor_ids=tuple(f.floor_id for f in floors),
        floor_index=floor_index,
        transmitter_index=tables["transmitter"].index(),
        anchor_index=tables["anchor"].index(),
        locator_index=tables["locator"].index(),
        zones=tuple(zones),
        engine=site.engine or "hmm",
        radio_maps=radio_maps,
        tuning=tuning,
    )
