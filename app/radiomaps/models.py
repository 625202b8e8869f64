"""Built radio maps, their survey guidance, calibrated transmitters and radio-map build jobs."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import (
    JSON,
    Boolean,
    Float,
    ForeignKey,
    ForeignKeyConstraint,
    Integer,
    LargeBinary,
    String,
    Text,
)
from sqlalchemy.orm import Mapped, mapped_column

from app.core.db import Base, UtcDateTime
from app.core.time import utcnow


class RadioMapBuild(Base):
    """The site's latest build: its summary (one row per site, replaced by each build)."""

    __tablename__ = "radiomap_builds"

    site_id: Mapped[str] = mapped_column(
        String(64), ForeignKey("sites.id", ondelete="CASCADE"), primary_key=True
    )
    summary: Mapped[dict] = mapped_column(JSON)
    built_at: Mapped[datetime] = mapped_column(UtcDateTime(), default=utcnow)


class RadioMapFloor(Base):
    """One floor's fingerprint map: ``data`` is the npz of ``RadioMap.to_arrays()``.

    ``transmitters`` names the map's columns by transmitter id, so the map
    survives changes of the site's transmitter table order.
    """

    __tablename__ = "radiomap_floors"
    __table_args__ = (
        ForeignKeyConstraint(
            ["site_id", "floor_id"], ["floors.site_id", "floors.floor_id"], ondelete="CASCADE"
        ),
    )

    site_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    floor_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    n_points: Mapped[int] = mapped_column(Integer)
    transmitters: Mapped[list] = mapped_column(JSON)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class SurveyGuidanceFloor(Base):
    """One floor's survey guidance from the latest build: ``data`` is the npz of its
    expected-error grid (``app.radiomaps.codec.encode_guidance``)."""

    __tablename__ = "survey_guidance_floors"
    __table_args__ = (
        ForeignKeyConstraint(
            ["site_id", "floor_id"], ["floors.site_id", "floors.floor_id"], ondelete="CASCADE"
        ),
    )

    site_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    floor_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class CalibratedTransmitter(Base):
    """A transmitter's fitted path loss (and position, unless the map gives it)."""

    __tablename__ = "calibrated_transmitters"
    __table_args__ = (
        ForeignKeyConstraint(
            ["site_id", "floor_id"], ["floors.site_id", "floors.floor_id"], ondelete="CASCADE"
        ),
    )

    site_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    transmitter_id: Mapped[str] = mapped_column(String(128), primary_key=True)
    floor_id: Mapped[str] = mapped_column(String(64))
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    z: Mapped[float] = mapped_column(Float)
    A: Mapped[float] = mapped_column(Float)
    B: Mapped[float] = mapped_column(Float)
    sigma: Mapped[float] = mapped_column(Float)
    n_readings: Mapped[int] = mapped_column(Integer)
    n_censored: Mapped[int] = mapped_column(Integer)
    spread_m: Mapped[float] = mapped_column(Float)
    converged: Mapped[bool] = mapped_column(Boolean)
    plausible: Mapped[bool] = mapped_column(Boolean)
    position_known: Mapped[bool] = mapped_column(Boolean)


class RadioMapJob(Base):
    """An asynchronous build: queued, running, done or failed, with its progress."""

    __tablename__ = "radiomap_jobs"

    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    site_id: Mapped[str] = mapped_column(
        String(64), ForeignKey("sites.id", ondelete="CASCADE"), index=True
    )
    status: Mapped[str] = mapped_column(String(16), index=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    summary: Mapped[dict | None] = mapped_column(JSON)
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime(), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime(), default=utcnow, onupdate=utcnow)
    """Renewed while a process runs the build (``app.core.jobs``)."""
