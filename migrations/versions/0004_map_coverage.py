"""map coverage: how far a map speaks for the ground, for localization at its edge

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-07 01:50:00

A map's markings' convex hull was taken as the ground it holds every marking
of. A map of a route, or of separate parts of a city, ends inside its hull:
such a map says so with ``coverage = 'markings'``. NULL (every map before):
as the server is set (``LANEMAP_MAP_COVERAGE``, by default the hull).
"""
from alembic import op
import sqlalchemy as sa


revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('maps') as batch_op:
        batch_op.add_column(sa.Column('coverage', sa.String(length=16), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('maps') as batch_op:
        batch_op.drop_column('coverage')
