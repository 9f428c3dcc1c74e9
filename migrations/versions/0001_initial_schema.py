"""initial schema

Revision ID: 0001
Revises: 
Create Date: 2026-11-22 04:19:11.951833
"""
from alembic import op
import sqlalchemy as sa


revision = '0001'
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table('maps',
    sa.Column('id', sa.String(length=64), nullable=False),
    sa.Column('title', sa.String(length=200), nullable=False),
    sa.Column('crs', sa.String(length=64), nullable=True),
    sa.Column('minx', sa.Float(), nullable=True),
    sa.Column('miny', sa.Float(), nullable=True),
    sa.Column('maxx', sa.Float(), nullable=True),
    sa.Column('maxy', sa.Float(), nullable=True),
    sa.Column('revision', sa.Integer(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('updated_at', sa.DateTime(timezone=True), nullable=False),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_maps'))
    )
    op.create_table('changesets',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('map_id', sa.String(length=64), nullable=False),
    sa.Column('who', sa.String(length=120), nullable=False),
    sa.Column('at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('comment', sa.Text(), nullable=False),
    sa.Column('n_create', sa.Integer(), nullable=False),
    sa.Column('n_update', sa.Integer(), nullable=False),
    sa.Column('n_delete', sa.Integer(), nullable=False),
    sa.Column('reverts', sa.Integer(), nullable=True),
    sa.ForeignKeyConstraint(['map_id'], ['maps.id'], name=op.f('fk_changesets_map_id_maps'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_changesets')),
    sqlite_autoincrement=True
    )
    with op.batch_alter_table('changesets', schema=None) as batch_op:
        batch_op.create_index('ix_changesets_map', ['map_id', 'id'], unique=False)

    op.create_table('imagery',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('map_id', sa.String(length=64), nullable=False),
    sa.Column('path', sa.Text(), nullable=False),
    sa.Column('crs', sa.String(length=64), nullable=False),
    sa.Column('minx', sa.Float(), nullable=False),
    sa.Column('miny', sa.Float(), nullable=False),
    sa.Column('maxx', sa.Float(), nullable=False),
    sa.Column('maxy', sa.Float(), nullable=False),
    sa.Column('resolution_m', sa.Float(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['map_id'], ['maps.id'], name=op.f('fk_imagery_map_id_maps'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_imagery'))
    )
    op.create_table('jobs',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('kind', sa.String(length=32), nullable=False),
    sa.Column('map_id', sa.String(length=64), nullable=True),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('progress', sa.Float(), nullable=False),
    sa.Column('params', sa.JSON(), nullable=False),
    sa.Column('error', sa.Text(), nullable=True),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('updated_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('started_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('finished_at', sa.DateTime(timezone=True), nullable=True),
    sa.CheckConstraint("status IN ('accepted', 'running', 'successful', 'failed', 'dismissed')", name=op.f('ck_jobs_status')),
    sa.ForeignKeyConstraint(['map_id'], ['maps.id'], name=op.f('fk_jobs_map_id_maps'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_jobs')),
    sqlite_autoincrement=True
    )
    op.create_table('markings',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('map_id', sa.String(length=64), nullable=False),
    sa.Column('tile_key', sa.String(length=128), nullable=True),
    sa.Column('gx', sa.Integer(), nullable=False),
    sa.Column('gy', sa.Integer(), nullable=False),
    sa.Column('x', sa.Float(), nullable=False),
    sa.Column('y', sa.Float(), nullable=False),
    sa.Column('lon', sa.Float(), nullable=False),
    sa.Column('lat', sa.Float(), nullable=False),
    sa.Column('weight', sa.Float(), nullable=False),
    sa.Column('length_m', sa.Float(), nullable=False),
    sa.Column('width_m', sa.Float(), nullable=False),
    sa.Column('bearing_deg', sa.Float(), nullable=False),
    sa.Column('score', sa.Float(), nullable=True),
    sa.Column('kind', sa.String(length=32), nullable=True),
    sa.Column('source', sa.String(length=16), nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('x0', sa.Float(), nullable=True),
    sa.Column('y0', sa.Float(), nullable=True),
    sa.Column('x1', sa.Float(), nullable=True),
    sa.Column('y1', sa.Float(), nullable=True),
    sa.Column('extra', sa.JSON(), nullable=False),
    sa.Column('version', sa.Integer(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('updated_at', sa.DateTime(timezone=True), nullable=False),
    sa.CheckConstraint("source IN ('detected', 'manual', 'imported')", name=op.f('ck_markings_source')),
    sa.CheckConstraint("status IN ('unreviewed', 'accepted', 'rejected')", name=op.f('ck_markings_status')),
    sa.CheckConstraint('weight > 0', name=op.f('ck_markings_weight_positive')),
    sa.ForeignKeyConstraint(['map_id'], ['maps.id'], name=op.f('fk_markings_map_id_maps'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_markings')),
    sqlite_autoincrement=True
    )
    with op.batch_alter_table('markings', schema=None) as batch_op:
        batch_op.create_index('ix_markings_grid', ['map_id', 'gx', 'gy', 'x', 'y'], unique=False)
        batch_op.create_index('ix_markings_tile', ['map_id', 'tile_key', 'source', 'status'], unique=False)

    op.create_table('edits',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('map_id', sa.String(length=64), nullable=False),
    sa.Column('changeset_id', sa.Integer(), nullable=False),
    sa.Column('marking_id', sa.Integer(), nullable=True),
    sa.Column('op', sa.String(length=16), nullable=False),
    sa.Column('who', sa.String(length=120), nullable=False),
    sa.Column('at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('before', sa.JSON(), nullable=True),
    sa.Column('after', sa.JSON(), nullable=True),
    sa.Column('comment', sa.Text(), nullable=False),
    sa.CheckConstraint("op IN ('create', 'update', 'delete', 'import')", name=op.f('ck_edits_op')),
    sa.ForeignKeyConstraint(['changeset_id'], ['changesets.id'], name=op.f('fk_edits_changeset_id_changesets'), ondelete='CASCADE'),
    sa.ForeignKeyConstraint(['map_id'], ['maps.id'], name=op.f('fk_edits_map_id_maps'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_edits'))
    )
    with op.batch_alter_table('edits', schema=None) as batch_op:
        batch_op.create_index('ix_edits_changeset', ['changeset_id'], unique=False)
        batch_op.create_index('ix_edits_map', ['map_id', 'id'], unique=False)

    op.create_table('job_tiles',
    sa.Column('job_id', sa.Integer(), nullable=False),
    sa.Column('tile_key', sa.String(length=128), nullable=False),
    sa.Column('n_markings', sa.Integer(), nullable=False),
    sa.Column('done_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['job_id'], ['jobs.id'], name=op.f('fk_job_tiles_job_id_jobs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('job_id', 'tile_key', name=op.f('pk_job_tiles'))
    )


def downgrade() -> None:
    op.drop_table('job_tiles')
    with op.batch_alter_table('edits', schema=None) as batch_op:
        batch_op.drop_index('ix_edits_map')
        batch_op.drop_index('ix_edits_changeset')

    op.drop_table('edits')
    with op.batch_alter_table('markings', schema=None) as batch_op:
        batch_op.drop_index('ix_markings_tile')
        batch_op.drop_index('ix_markings_grid')

    op.drop_table('markings')
    op.drop_table('jobs')
    op.drop_table('imagery')
    with op.batch_alter_table('changesets', schema=None) as batch_op:
        batch_op.drop_index('ix_changesets_map')

    op.drop_table('changesets')
    op.drop_table('maps')
