"""Floors: validate, store and read floor maps."""

from __future__ import annotations

from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.errors import Invalid, NotFound
from app.engine.plan import NoFreeCell
from app.floors.models import FloorRecord
from app.geometry.extent import ExtentLimits, extent_problems
from app.geometry.floormap import FloorMapError, Problem, parse_floor_map, summarize
from app.geometry.raster import floor_plan
from app.sites.models import Site
from app.sites.service import bump_map_version


def get_floor(*, db: Session, site_id: str, floor_id: str) -> FloorRecord | None:
    """Return the floor or None."""
    return db.get(FloorRecord, (site_id, floor_id))


def require_floor(*, db: Session, site_id: str, floor_id: str) -> FloorRecord:
    """Return the floor or raise NotFound."""
    floor = get_floor(db=db, site_id=site_id, floor_id=floor_id)
    if floor is None:
        raise NotFound(f"floor '{floor_id}' not found in site '{site_id}'")
    return floor


def list_floors(*, db: Session, site_id: str) -> list[FloorRecord]:
    """Return the site's floors ordered by level."""
    rows = db.scalars(
        select(FloorRecord).where(FloorRecord.site_id == site_id).order_by(FloorRecord.level)
    )
    return list(rows)


def _rejected(problems: list[Problem]) -> Invalid:
    return Invalid(
        f"floor map rejected: {len(problems)} problem(s)",
        code="invalid_floor_map",
        details=[p.as_dict() for p in problems],
    )


def put_floor(
    *, db: Session, site: Site, floor_id: str, doc: dict[str, Any], limits: ExtentLimits
) -> FloorRecord:
    """Validate ``doc`` and its size (Invalid listing every problem), rasterise and store it."""
    try:
        fmap = parse_floor_map(doc)
    except FloorMapError as exc:
        raise _rejected(exc.problems) from exc
    problems = extent_problems(doc, limits)
    if problems:
        raise _rejected(problems)
    try:
        plan = floor_plan(fmap, cell=limits.cell)
    except NoFreeCell as exc:
        reason = (
            f"the walkable area (outline less barriers) covers no raster cell of {limits.cell:g} "
            "m: it is narrower than a cell everywhere"
        )
        raise _rejected([Problem(None, "outline", reason)]) from exc
    summary = summarize(fmap) | {
        "raster": {
            "cell": plan.cell,
            "shape": list(plan.shape),
            "free_cells": int(np.count_nonzero(plan.free)),
        }
    }
    floor = get_floor(db=db, site_id=site.id, floor_id=floor_id)
    if floor is None:
        floor = FloorRecord(site_id=site.id, floor_id=floor_id)
        db.add(floor)
    floor.level = fmap.level
    floor.height = fmap.height
    floor.name = fmap.name
    floor.geojson = doc
    floor.summary = summary
    bump_map_version(db=db, site=site)
    db.flush()
    return floor


def delete_floor(*, db: Session, site: Site, floor: FloorRecord) -> None:
    """Remove a floor from the site."""
    db.delete(floor)
    bump_map_version(db=db, site=site)
    db.flush()
