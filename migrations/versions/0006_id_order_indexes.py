"""indexes for reading a map's markings in id order and a marking's edits

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-07 19:40:00

``ix_markings_map (map_id, id)``: a page of a map's markings by id (``/items``
without a box), and an export, read in index order; SQLite sorted the whole
map for each page. ``ix_edits_marking (map_id, marking_id, id)``: the history
of one marking (``/history?feature=``) read without scanning the map's edit
log. Building them reads each table once (about a second per million rows).
"""
from alembic import op


revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index('ix_markings_map', 'markings', ['map_id', 'id'])
    op.create_index('ix_edits_marking', 'edits', ['map_id', 'marking_id', 'id'])


def downgrade() -> None:
    op.drop_index('ix_edits_marking', table_name='edits')
    op.drop_index('ix_markings_map', table_name='markings')
