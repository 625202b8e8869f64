"""Floors: a validated floor map (GeoJSON in the local frame) per site and floor id."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import JSON, Float, ForeignKey, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from app.core.db import Base, UtcDateTime
from app.core.time import utcnow


class FloorRecord(Base):
    """One floor of a site with its map as uploaded and the summary computed from it."""

    __tablename__ = "floors"

    site_id: Mapped[str] = mapped_column(
        String(64), ForeignKey("sites.id", ondelete="CASCADE"), primary_key=True
    )
    floor_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    level: Mapped[int] = mapped_column(Integer)
    height: Mapped[float] = mapped_column(Float)
    name: Mapped[str | None] = mapped_column(String(200))
    geojson: Mapped[dict] = mapped_column(JSON)
    summary: Mapped[dict] = mapped_column(JSON)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime(), default=utcnow, onupdate=utcnow)
