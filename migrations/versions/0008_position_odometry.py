"""positions keep the odometry their filter measured, so a stored track can be smoothed later

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-08 09:00:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    # nullable columns are added in place, on SQLite too: no copy of the history
    op.add_column("positions", sa.Column("odometry_x", sa.Float(), nullable=True))
    op.add_column("positions", sa.Column("odometry_y", sa.Float(), nullable=True))


def downgrade() -> None:
    """Revert this revision: the odometry goes, the positions stay."""
    with op.batch_alter_table("positions", schema=None) as batch_op:
        batch_op.drop_column("odometry_y")
        batch_op.drop_column("odometry_x")
