"""positions re-emitted refined by a smoother are kept beside the live ones, marked

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-06 10:00:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table("positions", schema=None) as batch_op:
        batch_op.add_column(
            sa.Column("smoothed", sa.Boolean(), nullable=False, server_default=sa.false())
        )


def downgrade() -> None:
    """Revert this revision: the refined positions go, the live ones stay."""
    positions = sa.table("positions", sa.column("smoothed", sa.Boolean))
    op.get_bind().execute(positions.delete().where(positions.c.smoothed.is_(True)))
    with op.batch_alter_table("positions", schema=None) as batch_op:
        batch_op.drop_column("smoothed")
