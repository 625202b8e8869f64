"""background jobs are held by a lease: tracks get updated_at; both job tables index status

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-05 10:00:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision: a track's lease starts from its creation."""
    with op.batch_alter_table("tracks", schema=None) as batch_op:
        batch_op.add_column(sa.Column("updated_at", sa.DateTime(timezone=True), nullable=True))
    tracks = sa.table("tracks", sa.column("created_at"), sa.column("updated_at"))
    op.get_bind().execute(tracks.update().values(updated_at=tracks.c.created_at))
    with op.batch_alter_table("tracks", schema=None) as batch_op:
        batch_op.alter_column(
            "updated_at", existing_type=sa.DateTime(timezone=True), nullable=False
        )
        batch_op.create_index(batch_op.f("ix_tracks_status"), ["status"], unique=False)
    with op.batch_alter_table("radiomap_jobs", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_radiomap_jobs_status"), ["status"], unique=False)


def downgrade() -> None:
    """Revert this revision."""
    with op.batch_alter_table("radiomap_jobs", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_radiomap_jobs_status"))
    with op.batch_alter_table("tracks", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_tracks_status"))
        batch_op.drop_column("updated_at")
