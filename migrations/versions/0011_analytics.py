"""zone events are stored, and positions are indexed by site and time, for analytics over a
site's whole history (occupancy of a zone, heatmaps of a floor, site-wide exports)

Revision ID: 0011
Revises: 0009
Create Date: 2026-12-07 18:40:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0011"
down_revision: str | None = "0010"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    op.create_table(
        "zone_events",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), primary_key=True),
        sa.Column("site_id", sa.String(64), nullable=False),
        sa.Column("zone", sa.String(200), nullable=False),
        sa.Column("device_id", sa.String(128), nullable=False),
        sa.Column("floor_id", sa.String(64), nullable=True),
        sa.Column("event", sa.String(8), nullable=False),
        sa.Column("t", sa.BigInteger(), nullable=False),
    )
    op.create_index(
        "ix_zone_events_site_zone_device_t",
        "zone_events",
        ["site_id", "zone", "device_id", "t", "event"],
        unique=True,
    )
    op.create_index("ix_zone_events_site_zone_t", "zone_events", ["site_id", "zone", "t"])
    # a heatmap or a site's export reads one time range of every device of the site
    op.create_index("ix_positions_site_t", "positions", ["site_id", "t"])


def downgrade() -> None:
    """Revert this revision: the zone events go, the positions stay."""
    op.drop_index("ix_positions_site_t", table_name="positions")
    op.drop_index("ix_zone_events_site_zone_t", table_name="zone_events")
    op.drop_index("ix_zone_events_site_zone_device_t", table_name="zone_events")
    op.drop_table("zone_events")
