"""Outputs (where a site's positions and zone events go) and their durable outbox."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import BigInteger, ForeignKey, Index, Integer, String, Text
from sqlalchemy.orm import Mapped, mapped_column

from app.core.db import Base, UtcDateTime
from app.core.time import utcnow


class Output(Base):
    """One configured output of a site: an MQTT broker or a webhook.

    ``secret`` is the MQTT password or the webhook's signing secret: the
    sender needs it as given, so it is kept, and never read into a response or
    a log line. ``delivered`` and ``failed`` are running totals; ``claimed_by``
    and ``claimed_until`` are the lease of the API node that delivers it, so
    that with several nodes each message is sent by one of them.
    """

    __tablename__ = "outputs"

    site_id: Mapped[str] = mapped_column(
        String(64), ForeignKey("sites.id", ondelete="CASCADE"), primary_key=True
    )
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    kind: Mapped[str] = mapped_column(String(16))
    url: Mapped[str] = mapped_column(String(2048))
    events: Mapped[str] = mapped_column(String(64))
    """The kinds of message it takes, comma-separated (``position``, ``zone``)."""
    options: Mapped[str] = mapped_column(Text, default="{}")
    """JSON of the kind's other settings (topic prefix, username, rate limit, ...)."""
    secret: Mapped[str | None] = mapped_column(String(1024), default=None)
    delivered: Mapped[int] = mapped_column(BigInteger, default=0)
    failed: Mapped[int] = mapped_column(BigInteger, default=0)
    last_error: Mapped[str | None] = mapped_column(Text, default=None)
    last_ok_at: Mapped[datetime | None] = mapped_column(UtcDateTime(), default=None)
    claimed_by: Mapped[str | None] = mapped_column(String(64), default=None)
    claimed_until: Mapped[datetime | None] = mapped_column(UtcDateTime(), default=None)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime(), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime(), default=utcnow, onupdate=utcnow)


class OutboxRow(Base):
    """One message waiting for one output, written with the position or event it carries.

    No foreign key to ``outputs``: a worker that has not yet seen an output's
    removal may still write rows for it, and that must not fail the
    transaction storing the positions; the dispatcher drops such rows.
    ``stored_at`` is epoch ms of the write (the retention bound counts from
    it); ``batch`` is the id of the first row of the webhook batch this row was
    first sent in, so that a retry sends the same batch under the same
    ``webhook-id``. Ids are never reused (AUTOINCREMENT on SQLite), so no later
    batch gets an id already sent.
    """

    __tablename__ = "outbox"
    __table_args__ = (
        Index("ix_outbox_output", "site_id", "output_id", "id"),
        {"sqlite_autoincrement": True},
    )

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    site_id: Mapped[str] = mapped_column(String(64))
    output_id: Mapped[str] = mapped_column(String(64))
    device_id: Mapped[str] = mapped_column(String(128))
    kind: Mapped[str] = mapped_column(String(16))
    payload: Mapped[str] = mapped_column(Text)
    stored_at: Mapped[int] = mapped_column(BigInteger)
    batch: Mapped[int | None] = mapped_column(BigInteger, default=None)
