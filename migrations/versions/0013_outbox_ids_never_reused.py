"""outbox ids are never reused: SQLite's outbox becomes AUTOINCREMENT

A webhook's ``webhook-id`` is named after the first outbox row of its batch, and a
receiver drops a message whose id it has seen. SQLite hands a table's next rowid as one
more than the largest present, so once an output's outbox was emptied the next message
got an id already sent. PostgreSQL's sequence never goes back; there nothing changes.

Revision ID: 0013
Revises: 0012
Create Date: 2026-12-08 10:00:00
"""

from collections.abc import Sequence

from alembic import op

revision: str = "0013"
down_revision: str | None = "0012"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision: rebuild SQLite's outbox with AUTOINCREMENT, its rows kept."""
    if op.get_bind().dialect.name != "sqlite":
        return
    with op.batch_alter_table(
        "outbox", recreate="always", table_kwargs={"sqlite_autoincrement": True}
    ):
        pass


def downgrade() -> None:
    """Revert this revision."""
    if op.get_bind().dialect.name != "sqlite":
        return
    with op.batch_alter_table(
        "outbox", recreate="always", table_kwargs={"sqlite_autoincrement": False}
    ):
        pass
