"""a device's position at a time is stored once: a batch processed twice (a worker that
lost its shard mid-round, a re-delivered stream entry) cannot store it again

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-10 09:00:00
"""

from collections.abc import Sequence

from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

KEY = ["site_id", "device_id", "t", "smoothed"]


def upgrade() -> None:
    """Apply this revision: keep the first of each repeated position, then forbid repeats."""
    op.execute(
        "DELETE FROM positions WHERE id NOT IN "
        f"(SELECT MIN(id) FROM positions GROUP BY {', '.join(KEY)})"
    )
    op.drop_index("ix_positions_site_device_t", table_name="positions")
    op.create_index("ix_positions_site_device_t", "positions", KEY, unique=True)


def downgrade() -> None:
    """Revert this revision: repeats are allowed again."""
    op.drop_index("ix_positions_site_device_t", table_name="positions")
    op.create_index("ix_positions_site_device_t", "positions", ["site_id", "device_id", "t"])
