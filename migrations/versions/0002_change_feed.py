"""change feed: the revision that last wrote each marking, removed markings, and how far back the feed goes

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-06 16:30:00

Markings written before this revision are stamped with their map's revision
at the time of the upgrade: a copy synchronised earlier gets them once more,
which is safe; no copy can miss one.
"""
from alembic import op
import sqlalchemy as sa


revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('maps', schema=None) as batch_op:
        batch_op.add_column(sa.Column('feed_since', sa.Integer(), server_default='0', nullable=False))
    with op.batch_alter_table('markings', schema=None) as batch_op:
        batch_op.add_column(sa.Column('revision', sa.Integer(), server_default='0', nullable=False))
    op.execute(
        "UPDATE markings SET revision = (SELECT maps.revision FROM maps WHERE maps.id = markings.map_id)"
    )
    with op.batch_alter_table('markings', schema=None) as batch_op:
        batch_op.create_index('ix_markings_revision', ['map_id', 'revision', 'id'], unique=False)

    op.create_table('removed_markings',
    sa.Column('map_id', sa.String(length=64), nullable=False),
    sa.Column('marking_id', sa.Integer(), nullable=False),
    sa.Column('revision', sa.Integer(), nullable=False),
    sa.Column('removed_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['map_id'], ['maps.id'], name=op.f('fk_removed_markings_map_id_maps'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('map_id', 'marking_id', name=op.f('pk_removed_markings'))
    )
    with op.batch_alter_table('removed_markings', schema=None) as batch_op:
        batch_op.create_index('ix_removed_markings_revision', ['map_id', 'revision', 'marking_id'], unique=False)


def downgrade() -> None:
    with op.batch_alter_table('removed_markings', schema=None) as batch_op:
        batch_op.drop_index('ix_removed_markings_revision')
    op.drop_table('removed_markings')
    with op.batch_alter_table('markings', schema=None) as batch_op:
        batch_op.drop_index('ix_markings_revision')
        batch_op.drop_column('revision')
    with op.batch_alter_table('maps', schema=None) as batch_op:
        batch_op.drop_column('feed_since')
