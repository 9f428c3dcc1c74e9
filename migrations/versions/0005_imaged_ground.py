"""imaged ground: the footprint of every built tile, for maps whose coverage is "imagery"

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-07 06:00:00

A build records, per tile, the ground its imagery shows (WKB polygon in the
map's CRS). A map with ``coverage = 'imagery'`` speaks for that ground and
for what its markings vouch for beyond it. Tiles built before this revision
have no record: build the image again to record its ground.
"""
from alembic import op
import sqlalchemy as sa


revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'imaged_ground',
        sa.Column('map_id', sa.String(length=64), nullable=False),
        sa.Column('tile_key', sa.String(length=128), nullable=False),
        sa.Column('footprint', sa.LargeBinary(), nullable=False),
        sa.Column('built_at', sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(['map_id'], ['maps.id'], name=op.f('fk_imaged_ground_map_id_maps'),
                                ondelete='CASCADE'),
        sa.PrimaryKeyConstraint('map_id', 'tile_key', name=op.f('pk_imaged_ground')),
    )


def downgrade() -> None:
    op.drop_table('imaged_ground')
