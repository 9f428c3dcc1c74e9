"""retired maps: the last revision of each deleted map, so that a map made anew under its id goes on from there

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-06 18:10:00

A map deleted and created again under the same id started again at revision
0. A copy of the old map (the change feed) or a server process's cache of it
(the localization index) that was at a revision the new map then reached
could not tell the two apart. The new map now goes on past the old one's
last revision, and its change feed answers only from there.
"""
from alembic import op
import sqlalchemy as sa


revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table('retired_maps',
    sa.Column('id', sa.String(length=64), nullable=False),
    sa.Column('revision', sa.Integer(), nullable=False),
    sa.Column('deleted_at', sa.DateTime(timezone=True), nullable=False),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_retired_maps'))
    )


def downgrade() -> None:
    op.drop_table('retired_maps')
