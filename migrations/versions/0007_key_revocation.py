"""API keys can be revoked: the row stays (listed with its revocation time), the key stops working

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-07 11:00:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table("api_keys", schema=None) as batch_op:
        batch_op.add_column(sa.Column("revoked_at", sa.DateTime(timezone=True), nullable=True))
        batch_op.create_index(batch_op.f("ix_api_keys_revoked_at"), ["revoked_at"], unique=False)


def downgrade() -> None:
    """Revert this revision: revoked keys are deleted, as the old schema cannot refuse them."""
    keys = sa.table("api_keys", sa.column("revoked_at", sa.DateTime))
    op.get_bind().execute(keys.delete().where(keys.c.revoked_at.is_not(None)))
    with op.batch_alter_table("api_keys", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_api_keys_revoked_at"))
        batch_op.drop_column("revoked_at")
