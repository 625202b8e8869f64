"""survey guidance: each floor's expected-error grid from the latest radio-map build's
held-out scans, replaced by every build

Revision ID: 0012
Revises: 0011
Create Date: 2026-12-09 10:00:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0012"
down_revision: str | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision: the survey guidance table (empty until the next build)."""
    op.create_table(
        "survey_guidance_floors",
        sa.Column("site_id", sa.String(length=64), nullable=False),
        sa.Column("floor_id", sa.String(length=64), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(
            ["site_id", "floor_id"],
            ["floors.site_id", "floors.floor_id"],
            name=op.f("fk_survey_guidance_floors_site_id_floors"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("site_id", "floor_id", name=op.f("pk_survey_guidance_floors")),
    )


def downgrade() -> None:
    """Revert this revision: the guidance goes, the radio maps stay."""
    op.drop_table("survey_guidance_floors")
