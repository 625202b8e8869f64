"""Exports of stored positions as CSV or GeoJSON, streamed a page of rows at a time.

The rows are read by keyset pagination (after the last ``(t, id)`` sent), each page
in its own short query, so a month of a device's history is never held at once and
no transaction stays open while a slow client reads.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Callable, Iterator
from typing import Literal

from fastapi.responses import StreamingResponse
from sqlalchemy import Select, or_, select
from sqlalchemy.orm import Session, sessionmaker

from app.positions.models import PositionRecord
from app.positions.service import history_query

Format = Literal["csv", "geojson"]
MEDIA_TYPES: dict[str, str] = {"csv": "text/csv; charset=utf-8", "geojson": "application/geo+json"}
COLUMNS = (
    "site_id",
    "device_id",
    "floor_id",
    "t",
    "x",
    "y",
    "z",
    "heading",
    "accuracy",
    "speed",
    "method",
    "smoothed",
)


def device_rows(site_id: str, device_id: str) -> Select[PositionRecord]:
    """Return the query of a device's history as its JSON pages give it (refined preferred)."""
    return history_query(site_id=site_id, device_id=device_id)


def site_rows(site_id: str) -> Select[PositionRecord]:
    """Return the query of every live position of a site."""
    return select(PositionRecord).where(
        PositionRecord.site_id == site_id, PositionRecord.smoothed.is_(False)
    )


def pages(
    sessions: sessionmaker[Session],
    query: Select[PositionRecord],
    *,
    t_from: int | None,
    t_to: int | None,
    page_rows: int,
) -> Iterator[list[PositionRecord]]:
    """Yield the rows of ``query`` with ``t_from <= t <= t_to`` in ``(t, id)`` order, a page
    at a time, each page read in a session of its own."""
    p = PositionRecord
    if t_from is not None:
        query = query.where(p.t >= t_from)
    if t_to is not None:
        query = query.where(p.t <= t_to)
    after: tuple[int, int] | None = None
    while True:
        page_query = query
        if after is not None:
            t, row_id = after
            page_query = query.where(or_(p.t > t, (p.t == t) & (p.id > row_id)))
        with sessions() as db:
            rows = list(db.scalars(page_query.order_by(p.t, p.id).limit(page_rows)))
            db.expunge_all()
        if not rows:
            return
        yield rows
        if len(rows) < page_rows:
            return
        after = (rows[-1].t, rows[-1].id)


def _values(row: PositionRecord) -> list[object]:
    return [getattr(row, c) for c in COLUMNS]


def csv_chunks(rows: Iterator[list[PositionRecord]]) -> Iterator[str]:
    """Yield a header line, then one CSV line per position, a page per chunk."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    yield _take(buffer)
    for page in rows:
        writer.writerows(_values(r) for r in page)
        yield _take(buffer)


def _feature(row: PositionRecord) -> str:
    properties = {c: getattr(row, c) for c in COLUMNS if c not in ("x", "y", "z")}
    point = {"type": "Point", "coordinates": [row.x, row.y, row.z]}
    return json.dumps({"type": "Feature", "geometry": point, "properties": properties})


def geojson_chunks(rows: Iterator[list[PositionRecord]]) -> Iterator[str]:
    """Yield a FeatureCollection of Points in the floor's local frame (m), a page per chunk."""
    yield '{"type": "FeatureCollection", "features": ['
    first = True
    for page in rows:
        chunk = ",\n".join(_feature(r) for r in page)
        yield chunk if first else ",\n" + chunk
        first = False
    yield "]}\n"


WRITERS: dict[str, Callable[[Iterator[list[PositionRecord]]], Iterator[str]]] = {
    "csv": csv_chunks,
    "geojson": geojson_chunks,
}


def _take(buffer: io.StringIO) -> str:
    text = buffer.getvalue()
    buffer.seek(0)
    buffer.truncate()
    return text


def response(
    sessions: sessionmaker[Session],
    query: Select[PositionRecord],
    format: str,
    *,
    t_from: int | None,
    t_to: int | None,
    page_rows: int,
) -> StreamingResponse:
    """Return the streamed export of ``query``'s rows with ``t_from <= t <= t_to``."""
    rows = pages(sessions, query, t_from=t_from, t_to=t_to, page_rows=page_rows)
    return StreamingResponse(WRITERS[format](rows), media_type=MEDIA_TYPES[format])
