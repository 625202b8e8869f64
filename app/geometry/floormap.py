"""Parse and validate a floor map (GeoJSON FeatureCollection in the local frame).

Validation collects every problem instead of stopping at the first, so an
admin fixing a map sees the whole list at once: each problem names the
feature index, its kind and the reason.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

import shapely
from shapely.errors import ShapelyError
from shapely.geometry import shape
from shapely.geometry.base import BaseGeometry
from shapely.validation import explain_validity

KINDS: dict[str, tuple[str, ...]] = {
    "outline": ("Polygon", "MultiPolygon"),
    "wall": ("LineString", "MultiLineString"),
    "barrier": ("Polygon", "MultiPolygon"),
    "room": ("Polygon",),
    "zone": ("Polygon",),
    "transmitter": ("Point",),
    "anchor": ("Point",),
    "locator": ("Point",),
}
TECHS = ("wifi", "ble", "ibeacon")
EMITTER_KINDS = ("transmitter", "anchor", "locator")


@dataclass(frozen=True)
class Problem:
    """One reason a map was rejected; ``index`` is the feature's position or None for the map."""

    index: int | None
    kind: str | None
    reason: str

    def as_dict(self) -> dict[str, Any]:
        """Return the JSON form used in the error's ``details``."""
        return {"index": self.index, "kind": self.kind, "reason": self.reason}


@dataclass(frozen=True)
class Emitter:
    """A point of radio infrastructure: transmitter, UWB anchor or locator."""

    kind: str
    id: str
    x: float
    y: float
    z: float
    tech: str | None = None
    A: float | None = None
    B: float | None = None
    sigma: float | None = None


@dataclass
class FloorMap:
    """A validated floor map as shapely geometries."""

    level: int
    height: float
    name: str | None
    georef: dict[str, float] | None
    outline: BaseGeometry
    walls: list[BaseGeometry] = field(default_factory=list)
    barriers: list[BaseGeometry] = field(default_factory=list)
    rooms: list[tuple[str, BaseGeometry]] = field(default_factory=list)
    zones: list[tuple[str, BaseGeometry]] = field(default_factory=list)
    emitters: list[Emitter] = field(default_factory=list)

    @property
    def walkable(self) -> BaseGeometry:
        """Return where a position may be: the outline minus every barrier."""
        if not self.barriers:
            return self.outline
        return shapely.difference(self.outline, shapely.union_all(self.barriers))

    def of_kind(self, kind: str) -> list[Emitter]:
        """Return the emitters of one kind (transmitter, anchor, locator)."""
        return [e for e in self.emitters if e.kind == kind]


class FloorMapError(ValueError):
    """The map is invalid; ``problems`` lists every reason."""

    def __init__(self, problems: list[Problem]) -> None:
        super().__init__(f"{len(problems)} problem(s) in floor map")
        self.problems = problems


def _finite_coords(geometry: dict[str, Any]) -> bool:
    def walk(node: Any) -> bool:
        if isinstance(node, list | tuple):
            return all(walk(n) for n in node)
        return isinstance(node, int | float) and not isinstance(node, bool) and math.isfinite(node)

    return walk(geometry.get("coordinates"))


_VALIDITY = {
    "Self-intersection": "its edges cross each other",
    "Ring Self-intersection": "a ring touches itself",
    "Hole lies outside shell": "a hole lies outside its polygon",
    "Holes are nested": "a hole lies inside another hole",
    "Interior is disconnected": "its holes cut it in pieces",
    "Nested shells": "one of its polygons lies inside another",
    "Duplicate Rings": "a ring repeats",
    "Too few points": "a ring or line has too few distinct points",
    "Invalid Coordinate": "a coordinate is not a number",
    "Ring is not closed": "a ring does not end where it starts",
}


def _invalidity(geom: BaseGeometry) -> str:
    """Return why a geometry is invalid in words, with the place shapely names."""
    raw = explain_validity(geom)
    match = re.fullmatch(r"(.+?)\[(\S+) (\S+)\]", raw)
    if match is None or match.group(1) not in _VALIDITY:
        return f"invalid geometry: {raw}"
    x, y = (float(v) for v in match.group(2, 3))
    return f"invalid geometry: {_VALIDITY[match.group(1)]} at ({x:g}, {y:g})"


def _open_ring(geometry: dict[str, Any]) -> str | None:
    """Return what is wrong with a polygon's rings (None: each is closed, with 4+ positions).

    GeoJSON rings repeat their first position last; shapely would close an open
    one silently, drawing an edge the map's author never drew.
    """
    coords = geometry.get("coordinates")
    polygons: list[Any] = list(coords or []) if geometry["type"] == "MultiPolygon" else [coords]
    for p, rings in enumerate(polygons):
        for r, ring in enumerate(rings or []):
            if len(ring) < 4 or list(ring[0]) != list(ring[-1]):
                where = f"ring {r}" if len(polygons) == 1 else f"ring {r} of polygon {p}"
                return f"{where} must be closed (last position = first) with at least 4 positions"
    return None


def _number(props: dict[str, Any], key: str) -> float | None:
    value = props.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"'{key}' must be a finite number")
    return float(value)


def _collection_properties(props: Any, problems: list[Problem]) -> tuple[int, float, Any, Any]:
    if not isinstance(props, dict):
        problems.append(Problem(None, None, "collection 'properties' must be an object"))
        return 0, 4.0, None, None
    level = props.get("level")
    if isinstance(level, bool) or not isinstance(level, int):
        problems.append(Problem(None, None, "'level' must be an integer"))
        level = 0
    height = props.get("height", 4.0)
    if isinstance(height, bool) or not isinstance(height, int | float) or not 0 < height < 100:
        problems.append(Problem(None, None, "'height' must be a number of metres in (0, 100)"))
        height = 4.0
    name = props.get("name")
    if name is not None and not isinstance(name, str):
        problems.append(Problem(None, None, "'name' must be a string"))
        name = None
    georef = props.get("georef")
    if georef is not None:
        ok = isinstance(georef, dict) and all(
            isinstance(georef.get(k), int | float) and math.isfinite(georef[k])
            for k in ("lon", "lat", "rotation_deg")
        )
        if not ok:
            problems.append(
                Problem(None, None, "'georef' must be {lon, lat, rotation_deg} finite numbers")
            )
            georef = None
    return level, float(height), name, georef


def _emitter(kind: str, coords: list[float], props: dict[str, Any]) -> Emitter:
    ident = props.get("id")
    if not isinstance(ident, str) or not ident.strip():
        raise ValueError("'id' must be a non-empty string")
    if kind in ("anchor", "locator") and len(coords) != 3:
        raise ValueError("a point [x, y, z] is required")
    if len(coords) not in (2, 3):
        raise ValueError("a point needs 2 or 3 coordinates")
    z = float(coords[2]) if len(coords) == 3 else 0.0
    tech = None
    A = B = sigma = None
    if kind == "transmitter":
        tech = props.get("tech")
        if tech not in TECHS:
            raise ValueError(f"'tech' must be one of {', '.join(TECHS)}")
        A, B, sigma = _number(props, "A"), _number(props, "B"), _number(props, "sigma")
        if B is not None and B <= 0:
            raise ValueError("'B' must be positive")
        if sigma is not None and sigma <= 0:
            raise ValueError("'sigma' must be positive")
        # MAC addresses and iBeacon UUIDs are hex: any case names the same transmitter
        ident = ident.lower()
    return Emitter(kind, ident, float(coords[0]), float(coords[1]), z, tech, A, B, sigma)


def parse_floor_map(doc: Any) -> FloorMap:
    """Validate a floor-map document and return it as geometries.

    Raises
    ------
    FloorMapError
        With every problem found; nothing is partially accepted.
    """
    problems: list[Problem] = []
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection":
        raise FloorMapError([Problem(None, None, "body must be a GeoJSON FeatureCollection")])
    features = doc.get("features")
    if not isinstance(features, list):
        raise FloorMapError([Problem(None, None, "'features' must be a list")])
    level, height, name, georef = _collection_properties(doc.get("properties"), problems)

    outlines: list[BaseGeometry] = []
    outline_features = 0
    fmap = FloorMap(level, height, name, georef, outline=shapely.Polygon())
    seen_ids: dict[str, int] = {}
    for index, feature in enumerate(features):
        kind = None
        try:
            if not isinstance(feature, dict) or feature.get("type") != "Feature":
                raise ValueError("not a GeoJSON Feature")
            props = feature.get("properties") or {}
            if not isinstance(props, dict):
                raise ValueError("'properties' must be an object")
            kind = props.get("kind")
            outline_features += kind == "outline"
            if kind not in KINDS:
                kind = None if not isinstance(kind, str) else kind
                raise ValueError(f"'kind' must be one of {', '.join(KINDS)}")
            geometry = feature.get("geometry")
            if not isinstance(geometry, dict) or geometry.get("type") not in KINDS[kind]:
                raise ValueError(f"geometry must be {' or '.join(KINDS[kind])}")
            if not _finite_coords(geometry):
                raise ValueError("coordinates must be finite numbers")
            if kind in EMITTER_KINDS:
                emitter = _emitter(kind, list(geometry["coordinates"]), props)
                if emitter.id in seen_ids:
                    raise ValueError(
                        f"id '{emitter.id}' repeats feature {seen_ids[emitter.id]} on this floor"
                    )
                seen_ids[emitter.id] = index
                fmap.emitters.append(emitter)
                continue
            ring_problem = _open_ring(geometry) if "Polygon" in geometry["type"] else None
            if ring_problem is not None:
                raise ValueError(ring_problem)
            geom = shape(geometry)
            if geom.is_empty:
                raise ValueError("geometry is empty")
            if not geom.is_valid:
                raise ValueError(_invalidity(geom))
            if kind in ("room", "zone"):
                label = props.get("name")
                if not isinstance(label, str) or not label.strip():
                    raise ValueError("'name' must be a non-empty string")
                (fmap.rooms if kind == "room" else fmap.zones).append((label, geom))
            elif kind == "outline":
                outlines.append(geom)
            elif kind == "wall":
                fmap.walls.append(geom)
            else:
                fmap.barriers.append(geom)
        except ShapelyError as exc:
            # GEOS refuses to build it at all (a line of one point)
            reason = str(exc).removeprefix("IllegalArgumentException: ")
            problems.append(Problem(index, kind, f"invalid geometry: {reason}"))
        except (ValueError, TypeError, AttributeError) as exc:
            problems.append(Problem(index, kind, str(exc)))
    # an outline feature that failed has its own problem above: count it, not just the good ones
    if outline_features != 1:
        problems.append(
            Problem(None, "outline", f"exactly one outline is required, found {outline_features}")
        )
    if problems:
        raise FloorMapError(problems)
    fmap.outline = outlines[0]
    if fmap.walkable.is_empty:
        raise FloorMapError([Problem(None, "barrier", "barriers cover the whole outline")])
    return fmap


def summarize(fmap: FloorMap) -> dict[str, Any]:
    """Return the upload answer's summary: bounds, areas and counts of each kind."""
    xmin, ymin, xmax, ymax = fmap.outline.bounds
    counts = {
        "wall": len(fmap.walls),
        "barrier": len(fmap.barriers),
        "room": len(fmap.rooms),
        "zone": len(fmap.zones),
    }
    for kind in EMITTER_KINDS:
        counts[kind] = len(fmap.of_kind(kind))
    return {
        "level": fmap.level,
        "height": fmap.height,
        "name": fmap.name,
        "bounds": [round(v, 3) for v in (xmin, ymin, xmax, ymax)],
        "outline_area": round(fmap.outline.area, 2),
        "walkable_area": round(fmap.walkable.area, 2),
        "counts": counts,
    }
