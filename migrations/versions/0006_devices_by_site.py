"""a device is known by (site, device id): snapshots keyed by both, a devices table, positions
indexed by both

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-07 10:00:00
"""

from collections.abc import Sequence
from datetime import UTC, datetime

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_positions = sa.table(
    "positions",
    sa.column("site_id", sa.String),
    sa.column("device_id", sa.String),
    sa.column("t", sa.BigInteger),
    sa.column("computed_at", sa.BigInteger),
)
_states = sa.table(
    "device_states",
    sa.column("site_id", sa.String),
    sa.column("device_id", sa.String),
    sa.column("t", sa.BigInteger),
    sa.column("updated_at", sa.DateTime),
)


def _epoch_ms(value: datetime) -> int:
    aware = value if value.tzinfo is not None else value.replace(tzinfo=UTC)
    return int(aware.timestamp() * 1000)


def upgrade() -> None:
    """Apply this revision; every stored position and snapshot keeps its site."""
    with op.batch_alter_table("device_states", schema=None) as batch_op:
        batch_op.drop_constraint("pk_device_states", type_="primary")
        batch_op.create_primary_key("pk_device_states", ["site_id", "device_id"])
    with op.batch_alter_table("positions", schema=None) as batch_op:
        batch_op.drop_index("ix_positions_device_t")
        batch_op.create_index("ix_positions_site_device_t", ["site_id", "device_id", "t"])
    devices = op.create_table(
        "devices",
        sa.Column("site_id", sa.String(length=64), nullable=False),
        sa.Column("device_id", sa.String(length=128), nullable=False),
        sa.Column("last_seen", sa.BigInteger(), nullable=False),
        sa.Column("last_t", sa.BigInteger(), nullable=False),
        sa.PrimaryKeyConstraint("site_id", "device_id", name=op.f("pk_devices")),
    )
    # the devices already heard: every (site, device) with a stored position or snapshot
    connection = op.get_bind()
    known: dict[tuple[str, str], tuple[int, int]] = {}
    heard = sa.select(
        _positions.c.site_id,
        _positions.c.device_id,
        sa.func.max(_positions.c.computed_at),
        sa.func.max(_positions.c.t),
    ).group_by(_positions.c.site_id, _positions.c.device_id)
    for site_id, device_id, seen, t in connection.execute(heard):
        known[(site_id, device_id)] = (int(seen), int(t))
    snapshots = sa.select(_states.c.site_id, _states.c.device_id, _states.c.updated_at, _states.c.t)
    for site_id, device_id, updated_at, t in connection.execute(snapshots):
        seen, last_t = known.get((site_id, device_id), (0, -1))
        known[(site_id, device_id)] = (max(seen, _epoch_ms(updated_at)), max(last_t, int(t)))
    if known:
        op.bulk_insert(
            devices,
            [
                {"site_id": s, "device_id": d, "last_seen": seen, "last_t": t}
                for (s, d), (seen, t) in sorted(known.items())
            ],
        )


def downgrade() -> None:
    """Revert this revision: where a device id has snapshots in several sites, the newest
    stays (the old key holds one per id); positions and their sites are kept."""
    op.drop_table("devices")
    with op.batch_alter_table("positions", schema=None) as batch_op:
        batch_op.drop_index("ix_positions_site_device_t")
        batch_op.create_index("ix_positions_device_t", ["device_id", "t"])
    connection = op.get_bind()
    rows = connection.execute(
        sa.select(_states.c.site_id, _states.c.device_id).order_by(
            _states.c.device_id, _states.c.updated_at.desc()
        )
    ).all()
    kept: set[str] = set()
    for site_id, device_id in rows:
        if device_id in kept:
            connection.execute(
                _states.delete().where(
                    _states.c.site_id == site_id, _states.c.device_id == device_id
                )
            )
        kept.add(device_id)
    with op.batch_alter_table("device_states", schema=None) as batch_op:
        batch_op.drop_constraint("pk_device_states", type_="primary")
        batch_op.create_primary_key("pk_device_states", ["device_id"])
