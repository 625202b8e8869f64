"""A worker's view of a site: the engine's SiteModel plus the id maps and zones around it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from shapely.geometry.base import BaseGeometry
from sqlalchemy.orm import Session

from app.engine.site import Emitters, Floor, SiteModel
from app.floors.service import list_floors
from app.geometry.floormap import Emitter, parse_floor_map
from app.geometry.raster import floor_plan
from app.sites.models import Site


@dataclass(frozen=True, eq=False)
class Zone:
    """A named geofence on one floor."""

    name: str
    floor: int
    polygon: BaseGeometry


@dataclass(frozen=True, eq=False)
class LoadedSite:
    """Everything a worker needs to turn a site's samples into positions."""

    site_id: str
    version: int
    config: dict[str, Any]
    model: SiteModel
    floor_ids: tuple[str, ...]
    floor_index: dict[str, int]
    transmitter_index: dict[str, int]
    anchor_index: dict[str, int]
    locator_index: dict[str, int]
    zones: tuple[Zone, ...]

    def has_pathloss(self) -> bool:
        """Return whether any transmitter has a complete path-loss model."""
        tx = self.model.transmitters
        return bool(len(tx)) and bool(np.isfinite(tx.A + tx.B + tx.sigma).any())


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


def load_site(*, db: Session, site: Site, raster_cell: float) -> LoadedSite:
    """Build the site's engine view from its stored floors."""
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
        config=dict(site.config or {}),
        model=model,
        floor_ids=tuple(f.floor_id for f in floors),
        floor_index={f.floor_id: i for i, f in enumerate(floors)},
        transmitter_index=tables["transmitter"].index(),
        anchor_index=tables["anchor"].index(),
        locator_index=tables["locator"].index(),
        zones=tuple(zones),
    )
