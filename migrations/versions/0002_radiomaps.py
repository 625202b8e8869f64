"""radio maps, calibrated transmitters, build jobs and the per-site engine choice

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-26 11:45:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table("sites", schema=None) as batch_op:
        batch_op.add_column(
            sa.Column("engine", sa.String(length=8), server_default="hmm", nullable=False)
        )
    op.create_table(
        "radiomap_builds",
        sa.Column("site_id", sa.String(length=64), nullable=False),
        sa.Column("summary", sa.JSON(), nullable=False),
        sa.Column("built_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["site_id"],
            ["sites.id"],
            name=op.f("fk_radiomap_builds_site_id_sites"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("site_id", name=op.f("pk_radiomap_builds")),
    )
    op.create_table(
        "radiomap_floors",
        sa.Column("site_id", sa.String(length=64), nullable=False),
        sa.Column("floor_id", sa.String(length=64), nullable=False),
        sa.Column("n_points", sa.Integer(), nullable=False),
        sa.Column("transmitters", sa.JSON(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(
            ["site_id", "floor_id"],
            ["floors.site_id", "floors.floor_id"],
            name=op.f("fk_radiomap_floors_site_id_floors"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("site_id", "floor_id", name=op.f("pk_radiomap_floors")),
    )
    op.create_table(
        "calibrated_transmitters",
        sa.Column("site_id", sa.String(length=64), nullable=False),
        sa.Column("transmitter_id", sa.String(length=128), nullable=False),
        sa.Column("floor_id", sa.String(length=64), nullable=False),
        sa.Column("x", sa.Float(), nullable=False),
        sa.Column("y", sa.Float(), nullable=False),
        sa.Column("z", sa.Float(), nullable=False),
        sa.Column("A", sa.Float(), nullable=False),
        sa.Column("B", sa.Float(), nullable=False),
        sa.Column("sigma", sa.Float(), nullable=False),
        sa.Column("n_readings", sa.Integer(), nullable=False),
        sa.Column("n_censored", sa.Integer(), nullable=False),
        sa.Column("spread_m", sa.Float(), nullable=False),
        sa.Column("converged", sa.Boolean(), nullable=False),
        sa.Column("plausible", sa.Boolean(), nullable=False),
        sa.Column("position_known", sa.Boolean(), nullable=False),
        sa.ForeignKeyConstraint(
            ["site_id", "floor_id"],
            ["floors.site_id", "floors.floor_id"],
            name=op.f("fk_calibrated_transmitters_site_id_floors"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint(
            "site_id", "transmitter_id", name=op.f("pk_calibrated_transmitters")
        ),
    )
    op.create_table(
        "radiomap_jobs",
        sa.Column("id", sa.String(length=36), nullable=False),
        sa.Column("site_id", sa.String(length=64), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("summary", sa.JSON(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["site_id"],
            ["sites.id"],
            name=op.f("fk_radiomap_jobs_site_id_sites"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_radiomap_jobs")),
    )
    with op.batch_alter_table("radiomap_jobs", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_radiomap_jobs_site_id"), ["site_id"], unique=False)


def downgrade() -> None:
    """Revert this revision."""
    with op.batch_alter_table("radiomap_jobs", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_radiomap_jobs_site_id"))
    op.drop_table("radiomap_jobs")
    op.drop_table("calibrated_transmitters")
    op.drop_table("radiomap_floors")
    op.drop_table("radiomap_builds")
    with op.batch_alter_table("sites", schema=None) as batch_op:
        batch_op.drop_column("engine")
