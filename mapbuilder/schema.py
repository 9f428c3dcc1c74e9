"""The database schema. Alembic (``migrations/``) creates and changes it; never ``create_all``.

Spatial index
-------------
Markings carry integer grid keys ``gx = floor(x / GRID_CELL_M)`` and
``gy = floor(y / GRID_CELL_M)`` and a composite B-tree index on
``(map_id, gx, gy, x, y)``. A bounding-box query restricts ``gx``/``gy`` to the
cells the box covers and filters ``x``/``y`` inside the index, so it touches
only the index entries of those grid columns, on SQLite and PostgreSQL alike
with the same SQL (no R*Tree module or PostGIS needed).
"""

from __future__ import annotations

from sqlalchemy import (
    JSON,
    CheckConstraint,
    Column,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Table,
    Text,
    text,
)

#: The markings of a map's review queue: the predicate of ``ix_markings_queue``, written out as SQL
#: so that a query holding it word for word can read the index.
QUEUED = "source = 'detected' AND status = 'unreviewed'"

#: Side of a grid cell of the spatial key, metres. About the size of a
#: typical query window's share of one lane; chosen by benchmarks/store_bbox.py.
GRID_CELL_M = 32.0

metadata = MetaData(
    naming_convention={
        "ix": "ix_%(table_name)s_%(column_0_N_name)s",
        "uq": "uq_%(table_name)s_%(column_0_N_name)s",
        "ck": "ck_%(table_name)s_%(constraint_name)s",
        "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
        "pk": "pk_%(table_name)s",
    }
)

maps = Table(
    "maps",
    metadata,
    Column("id", String(64), primary_key=True),
    Column("title", String(200), nullable=False, default=""),
    # NULL until chosen: set explicitly, or from the first data imported (its UTM zone).
    Column("crs", String(64)),
    Column("minx", Float),
    Column("miny", Float),
    Column("maxx", Float),
    Column("maxy", Float),
    Column("revision", Integer, nullable=False, default=0),
    # The oldest revision the change feed answers from (the deletions before it were pruned).
    Column("feed_since", Integer, nullable=False, default=0, server_default="0"),
    # How far the map speaks for the ground ("hull", "markings" or "imagery", store.MAP_COVERAGES);
    # NULL: as the server is set (LANEMAP_MAP_COVERAGE).
    Column("coverage", String(16)),
    Column("created_at", DateTime(timezone=True), nullable=False),
    Column("updated_at", DateTime(timezone=True), nullable=False),
)

markings = Table(
    "markings",
    metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("map_id", String(64), ForeignKey("maps.id", ondelete="CASCADE"), nullable=False),
    Column("tile_key", String(128)),
    Column("gx", Integer, nullable=False),
    Column("gy", Integer, nullable=False),
    Column("x", Float, nullable=False),
    Column("y", Float, nullable=False),
    Column("lon", Float, nullable=False),
    Column("lat", Float, nullable=False),
    Column("weight", Float, nullable=False, default=1.0),
    Column("length_m", Float, nullable=False, default=0.0),
    Column("width_m", Float, nullable=False, default=0.0),
    Column("bearing_deg", Float, nullable=False, default=0.0),
    Column("score", Float),
    Column("kind", String(32)),
    Column("source", String(16), nullable=False),
    Column("status", String(16), nullable=False),
    Column("x0", Float),
    Column("y0", Float),
    Column("x1", Float),
    Column("y1", Float),
    Column("extra", JSON, nullable=False, default=dict),
    Column("version", Integer, nullable=False, default=1),
    # The map revision that last wrote the marking: what GET .../changes?since= selects.
    Column("revision", Integer, nullable=False, default=0, server_default="0"),
    Column("created_at", DateTime(timezone=True), nullable=False),
    Column("updated_at", DateTime(timezone=True), nullable=False),
    CheckConstraint("source IN ('detected', 'manual', 'imported')", name="source"),
    CheckConstraint("status IN ('unreviewed', 'accepted', 'rejected')", name="status"),
    CheckConstraint("weight > 0", name="weight_positive"),
    Index("ix_markings_grid", "map_id", "gx", "gy", "x", "y"),
    Index("ix_markings_tile", "map_id", "tile_key", "source", "status"),
    Index("ix_markings_revision", "map_id", "revision", "id"),
    # A map's markings in id order: pages of /items and exports, without sorting the map.
    Index("ix_markings_map", "map_id", "id"),
    # The review queue, a map's unreviewed detections by score, without sorting them for every page;
    # partial: what is decided leaves it, and the rest of the map is not written to it.
    Index("ix_markings_queue", "map_id", "score", "id",
          sqlite_where=text(QUEUED), postgresql_where=text(QUEUED)),  # fmt: skip
    # Never reuse the id of a deleted marking: ids are feature ids and ETag scopes.
    sqlite_autoincrement=True,
)

#: How many markings each map holds by status, source, kind ('' where unknown) and score bin
#: (``floor(10 * score)`` up to 9; -1 without a score or below 0), kept by every write of
#: markings in its own transaction: a map's summary without reading its markings.
marking_counts = Table(
    "marking_counts",
    metadata,
    Column("map_id", String(64), ForeignKey("maps.id", ondelete="CASCADE"), primary_key=True),
    Column("status", String(16), primary_key=True),
    Column("source", String(16), primary_key=True),
    Column("kind", String(32), primary_key=True),
    Column("score_bin", Integer, primary_key=True, autoincrement=False),
    Column("n", Integer, nullable=False),
)

#: Markings deleted from a map, with the revision that deleted them, so that a
#: copy of the map kept elsewhere learns of deletions as well as of changes. An
#: id is live in ``markings`` or listed here, never both.
removed_markings = Table(
    "removed_markings",
    metadata,
    Column("map_id", String(64), ForeignKey("maps.id", ondelete="CASCADE"), primary_key=True),
    Column("marking_id", Integer, primary_key=True),
    Column("revision", Integer, nullable=False),
    Column("removed_at", DateTime(timezone=True), nullable=False),
    Index("ix_removed_markings_revision", "map_id", "revision", "marking_id"),
)

#: The last revision of each deleted map: a map created again under its id
#: goes on past it, so that nothing that knew the old map (a copy kept through
#: the change feed, a server process's cache) takes the new one for it.
retired_maps = Table(
    "retired_maps",
    metadata,
    Column("id", String(64), primary_key=True),
    Column("revision", Integer, nullable=False),
    Column("deleted_at", DateTime(timezone=True), nullable=False),
)

changesets = Table(
    "changesets",
    metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("map_id", String(64), ForeignKey("maps.id", ondelete="CASCADE"), nullable=False),
    Column("who", String(120), nullable=False),
    Column("at", DateTime(timezone=True), nullable=False),
    Column("comment", Text, nullable=False, default=""),
    Column("n_create", Integer, nullable=False, default=0),
    Column("n_update", Integer, nullable=False, default=0),
    Column("n_delete", Integer, nullable=False, default=0),
    Column("reverts", Integer),
    Index("ix_changesets_map", "map_id", "id"),
    sqlite_autoincrement=True,
)

edits = Table(
    "edits",
    metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("map_id", String(64), ForeignKey("maps.id", ondelete="CASCADE"), nullable=False),
    Column(
        "changeset_id",
        Integer,
        ForeignKey("changesets.id", ondelete="CASCADE"),
        nullable=False,
    ),
    Column("marking_id", Integer),  # no FK: the log outlives deleted markings
    Column("op", String(16), nullable=False),
    Column("who", String(120), nullable=False),
    Column("at", DateTime(timezone=True), nullable=False),
    Column("before", JSON),
    Column("after", JSON),
    Column("comment", Text, nullable=False, default=""),
    CheckConstraint("op IN ('create', 'update', 'delete', 'import')", name="op"),
    Index("ix_edits_map", "map_id", "id"),
    Index("ix_edits_changeset", "changeset_id"),
    Index("ix_edits_marking", "map_id", "marking_id", "id"),
)

imagery = Table(
    "imagery",
    metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("map_id", String(64), ForeignKey("maps.id", ondelete="CASCADE"), nullable=False),
    Column("path", Text, nullable=False),
    Column("crs", String(64), nullable=False),
    Column("minx", Float, nullable=False),
    Column("miny", Float, nullable=False),
    Column("maxx", Float, nullable=False),
    Column("maxy", Float, nullable=False),
    Column("resolution_m", Float, nullable=False),
    Column("created_at", DateTime(timezone=True), nullable=False),
)

jobs = Table(
    "jobs",
    metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("kind", String(32), nullable=False),
    Column("map_id", String(64), ForeignKey("maps.id", ondelete="CASCADE")),
    Column("status", String(16), nullable=False),
    Column("progress", Float, nullable=False, default=0.0),
    Column("params", JSON, nullable=False, default=dict),
    Column("error", Text),
    Column("created_at", DateTime(timezone=True), nullable=False),
    Column("updated_at", DateTime(timezone=True), nullable=False),
    Column("started_at", DateTime(timezone=True)),
    Column("finished_at", DateTime(timezone=True)),
    CheckConstraint(
        "status IN ('accepted', 'running', 'successful', 'failed', 'dismissed')", name="status"
    ),
    sqlite_autoincrement=True,
)

job_tiles = Table(
    "job_tiles",
    metadata,
    Column("job_id", Integer, ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True),
    Column("tile_key", String(128), primary_key=True),
    Column("n_markings", Integer, nullable=False, default=0),
    Column("done_at", DateTime(timezone=True), nullable=False),
)

# The ground each tile of a build imaged (WKB polygon, map CRS), whichever job
# built it last: a map whose coverage is "imagery" speaks for this ground.
# Kept apart from job_tiles so that it outlives the jobs.
imaged_ground = Table(
    "imaged_ground",
    metadata,
    Column("map_id", String(64), ForeignKey("maps.id", ondelete="CASCADE"), primary_key=True),
    Column("tile_key", String(128), primary_key=True),
    Column("footprint", LargeBinary, nullable=False),
    Column("built_at", DateTime(timezone=True), nullable=False),
)
