"""sites keep their engine choice in one column: drop config, which only repeated it

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-04 10:00:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table("sites", schema=None) as batch_op:
        batch_op.drop_column("config")


def downgrade() -> None:
    """Revert this revision: config comes back as ``{"engine": engine}``."""
    with op.batch_alter_table("sites", schema=None) as batch_op:
        batch_op.add_column(sa.Column("config", sa.JSON(), nullable=True))
    sites = sa.table(
        "sites", sa.column("id", sa.String), sa.column("engine", sa.String), sa.column("config")
    )
    connection = op.get_bind()
    for site_id, engine in connection.execute(sa.select(sites.c.id, sites.c.engine)).all():
        connection.execute(
            sites.update()
            .where(sites.c.id == site_id)
            .values(config=sa.literal({"engine": engine}, sa.JSON()))
        )
    with op.batch_alter_table("sites", schema=None) as batch_op:
        batch_op.alter_column("config", existing_type=sa.JSON(), nullable=False)
