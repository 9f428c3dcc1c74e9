"""The map store on a real SQLite file and a real PostgreSQL server."""

from __future__ import annotations

import json
import math
import multiprocessing as mp

import numpy as np
import pytest
from sqlalchemy import text

from mapbuilder import migrate
from mapbuilder.model import Marking
from mapbuilder.schema import GRID_CELL_M
from mapbuilder.store import (
    MAP_COVERAGES,
    INSERT_BATCH,
    Change,
    ConflictError,
    InvalidMarkingError,
    MapExistsError,
    SchemaError,
    Store,
    StoreError,
    UnknownJobError,
    UnknownMapError,
    UnknownMarkingError,
)

E0, N0 = 457000.0, 5428000.0  # Karlsruhe, EPSG:25832


def _m(dx: float, dy: float, **kw) -> Marking:
    return Marking(x=E0 + dx, y=N0 + dy, length_m=3.0, width_m=0.12, weight=36, **kw)


def _count(store: Store, map_id: str) -> int:
    return store.get_map(map_id, with_count=True).count


def test_empty_database_is_upgraded_on_first_use(db_url):
    store = Store(db_url)
    assert store.schema_revision() == migrate.head_revision()
    with store.engine.connect() as conn:
        tables = set(store.engine.dialect.get_table_names(conn))
    assert {"maps", "markings", "edits", "changesets", "imagery", "jobs", "job_tiles"} <= tables
    # A second open finds the schema current and changes nothing.
    assert Store(db_url).schema_revision() == migrate.head_revision()


def test_sqlite_connection_settings(sqlite_url):
    store = Store(sqlite_url)
    with store.engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
        assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() >= 1000


def test_unknown_schema_revision_is_refused(db_url):
    Store(db_url)
    store = Store(db_url)
    with store.engine.begin() as conn:
        conn.execute(text("UPDATE alembic_version SET version_num = 'ffff'"))
    with pytest.raises(SchemaError, match="lanemap db upgrade"):
        Store(db_url)


def test_map_lifecycle(store):
    info = store.create_map("ka", "Karlsruhe", "EPSG:25832")
    assert (info.id, info.title, info.crs, info.bounds, info.revision) == (
        "ka", "Karlsruhe", "EPSG:25832", None, 0,
    )  # fmt: skip
    with pytest.raises(MapExistsError, match="'ka' already exists"):
        store.create_map("ka")
    with pytest.raises(StoreError, match="invalid map id"):
        store.create_map("no spaces/slashes")
    with pytest.raises(StoreError, match="not projected"):
        store.create_map("geo", crs="EPSG:4326")
    store.add_markings("ka", [_m(0, 0), _m(10, 20)])
    assert [(i.id, i.count) for i in store.list_maps()] == [("ka", 2)]
    assert store.get_map("ka").bounds == (E0, N0, E0 + 10, N0 + 20)
    store.delete_map("ka")
    with pytest.raises(UnknownMapError, match="unknown map 'ka'"):
        store.get_map("ka")
    with pytest.raises(UnknownMapError, match="unknown map 'ka'"):
        store.map_revision("ka")
    with store.engine.connect() as conn:  # cascaded, nothing left behind
        assert conn.execute(text("SELECT count(*) FROM markings")).scalar() == 0
        assert conn.execute(text("SELECT count(*) FROM edits")).scalar() == 0


def test_a_maps_head_says_when_it_last_changed(store):
    """The head's ``updated`` moves with every write, its revision only with writes to markings:
    together they tell the same revision of a map written twice apart."""
    store.create_map("ka", crs="EPSG:25832")
    first = store.map_head("ka")
    store.add_markings("ka", [_m(0, 0)])
    second = store.map_head("ka")
    assert second.revision == first.revision + 1 and second.updated != first.updated
    assert second.created == first.created
    store.update_map("ka", title="Karlsruhe")
    third = store.map_head("ka")
    assert third.revision == second.revision and third.updated != second.updated
    assert third.updated.endswith("+00:00") and store.get_map("ka").updated_at.isoformat() == third.updated
    # the same whichever way it is read: the driver's own statement, or SQLAlchemy's when that fails
    engine = store.engine

    class NoRawConnection:
        def __getattr__(self, name):
            if name == "raw_connection":
                raise OSError("driver gone")
            return getattr(engine, name)

    store.engine = NoRawConnection()
    try:
        assert store.map_head("ka") == third
    finally:
        store.engine = engine


def test_a_maps_arrays_are_its_markings_by_id_and_status(store, monkeypatch):
    """``marking_arrays`` (what an index is built from), read straight from the driver in parts
    of ``_ARRAYS_PART``, holds each marking the status filter keeps, in id order, as the store's
    other reads give it."""
    import mapbuilder.store as store_module

    monkeypatch.setattr(store_module, "_ARRAYS_PART", 7)  # several parts, the last one short
    store.create_map("ka", crs="EPSG:25832")
    kinds = [None, "dash", "solid", "stop_line"]
    store.add_markings("ka", [_m(3.0 * k, 0.5 * k, kind=kinds[k % 4], bearing_deg=10.0 * k,
                                 status="rejected" if k % 5 == 0 else "unreviewed") for k in range(23)])
    store.create_map("empty", crs="EPSG:25832")
    want = [m for m in store.iter_markings("ka") if m.status != "rejected"]
    got = store.marking_arrays("ka")
    assert got.id.tolist() == sorted(m.id for m in want) == [m.id for m in want]
    for name in ("x", "y", "weight", "length_m", "bearing_deg"):
        assert np.allclose(getattr(got, name), [getattr(m, name) for m in want]), name
    assert got.kind.tolist() == [m.kind for m in want] and got.source.tolist() == [m.source for m in want]
    assert len(store.marking_arrays("ka", statuses=("rejected",))) == 23 - len(want)
    assert len(store.marking_arrays("ka", statuses=())) == 0 and len(store.marking_arrays("empty")) == 0
    with pytest.raises(UnknownMapError):
        store.marking_arrays("nope")


def test_a_maps_coverage_is_kept_and_checked(store):
    """How far a map speaks for the ground: its own (``hull`` or ``markings``) or None (the
    server's); setting it moves neither its markings nor its revision."""
    info = store.create_map("route", crs="EPSG:25832", coverage="markings")
    assert info.coverage == "markings" and store.map_head("route")[:2] == (0, "markings")
    store.add_markings("route", [_m(0, 0)])
    rev = store.map_revision("route")
    assert store.set_coverage("route", "hull").coverage == "hull"
    assert store.set_coverage("route", None).coverage is None
    assert store.map_head("route")[:2] == (rev, None)
    with pytest.raises(StoreError, match="coverage: must be one of hull, markings"):
        store.set_coverage("route", "convex")
    with pytest.raises(StoreError, match="coverage: must be one of hull, markings"):
        store.create_map("other", coverage="Hull")
    assert [i.id for i in store.list_maps()] == ["route"]
    with pytest.raises(UnknownMapError):
        store.set_coverage("nowhere", "hull")
    # a title and a coverage are written together, or neither
    with pytest.raises(StoreError, match="title: at most"):
        store.update_map("route", title="x" * 501, coverage="markings", set_coverage=True)
    assert store.get_map("route").coverage is None
    info = store.update_map("route", title="Route 1", coverage="markings", set_coverage=True)
    assert (info.title, info.coverage) == ("Route 1", "markings")
    assert store.update_map("route", title="Route 2").coverage == "markings"


def test_a_map_made_empty_takes_a_coverage_only_while_it_holds_nothing(store):
    """``adopt_coverage``: a first build's ``imagery`` goes to a map that holds no markings, no
    recorded ground and no coverage of its own; any of those, and the map keeps what it has.
    A map whose markings were all deleted holds nothing again."""
    import shapely

    store.create_map("empty", crs="EPSG:25832")
    assert store.adopt_coverage("empty", "imagery") == "imagery"
    assert store.map_head("empty")[:2] == (0, "imagery")  # no revision: nothing in it moved
    assert store.adopt_coverage("empty", "hull") == "imagery"  # set now: kept
    store.create_map("said", crs="EPSG:25832", coverage="markings")
    assert store.adopt_coverage("said", "imagery") == "markings"
    store.create_map("held", crs="EPSG:25832")
    (held,) = store.add_markings("held", [_m(0, 0)])
    assert store.adopt_coverage("held", "imagery") is None  # imported markings: the server's say
    assert store.get_map("held").coverage is None
    store.apply_changeset("held", [Change("delete", id=held, version=1)], who="bob")
    assert store.adopt_coverage("held", "imagery") == "imagery"
    store.create_map("ground", crs="EPSG:25832")
    store.replace_detected("ground", "t0", [], ground=shapely.to_wkb(shapely.box(0, 0, 10, 10)))
    assert store.adopt_coverage("ground", "imagery") is None
    with pytest.raises(StoreError, match="coverage: must be one of"):
        store.adopt_coverage("ground", "convex")
    with pytest.raises(UnknownMapError):
        store.adopt_coverage("nowhere", "imagery")


def test_the_coverages_a_map_may_say_are_the_extents_the_localizer_draws():
    """The store (which imports nothing of the localizer's), the server's setting and the API
    name the same values: the localizer's extent rules, and ``imagery`` (the markings' rule
    joined to the ground the map's builds imaged)."""
    from typing import get_args

    from localizer import EXTENT_RULES
    from service.routers.collections import CollectionIn
    from service.settings import ServiceSettings

    assert MAP_COVERAGES == (*EXTENT_RULES, "imagery")
    assert get_args(ServiceSettings.model_fields["map_coverage"].annotation) == MAP_COVERAGES
    assert get_args(get_args(CollectionIn.model_fields["coverage"].annotation)[0]) == MAP_COVERAGES


def test_maps_from_before_the_coverage_cover_as_the_server_is_set(db_url):
    old = Store(db_url, upgrade=False)
    old.upgrade("0003")
    with old.engine.begin() as conn:
        conn.execute(text("INSERT INTO maps (id, title, crs, revision, created_at, updated_at) "
                          "VALUES ('old', '', 'EPSG:25832', 7, CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"))
    old.close()
    up = Store(db_url, upgrade=False)
    assert up.upgrade() == ("0003", migrate.head_revision())
    up.close()
    store = Store(db_url)
    assert store.get_map("old").coverage is None and store.map_head("old")[:2] == (7, None)
    store.close()


def test_add_markings_fills_lonlat_and_is_all_or_nothing(store):
    store.create_map("ka", crs="EPSG:25832")
    ids = store.add_markings("ka", [_m(0, 0), _m(5, 5)], who="alice", comment="first")
    m = store.get_marking("ka", ids[0])
    assert m.version == 1 and m.source == "imported" and m.status == "unreviewed"
    assert 8.3 < m.lon < 8.5 and 48.9 < m.lat < 49.1
    bad = [_m(1, 1), Marking(x=E0, y=N0, weight=0)]
    with pytest.raises(InvalidMarkingError, match="marking 1: weight must be > 0"):
        store.add_markings("ka", bad)
    with pytest.raises(InvalidMarkingError, match="x must be finite"):
        store.add_markings("ka", [_m(1, 1), Marking(x=math.nan, y=N0)])
    with pytest.raises(InvalidMarkingError, match="source must be one of"):
        store.add_markings("ka", [Marking(x=E0, y=N0, source="guessed")])
    assert _count(store, "ka") == 2
    history, total = store.history("ka")
    assert total == 1 and history[0].op == "import" and history[0].after["count"] == 2
    assert history[0].who == "alice" and history[0].comment == "first"



def test_an_import_written_batch_by_batch_is_still_all_or_nothing(store):
    """An import writes a batch at a time: a marking found invalid after two batches were
    written leaves nothing of it, and one that succeeds counts and bounds every batch."""
    store.create_map("ka", crs="EPSG:25832")
    store.add_markings("ka", [_m(0, 0)])
    before = store.get_map("ka", with_count=True)
    n = 2 * INSERT_BATCH + 3
    bad = [_m(float(k % 500), float(k // 500), kind="dash") for k in range(n)]
    bad[-2] = Marking(x=E0, y=N0, weight=-1)
    with pytest.raises(InvalidMarkingError, match=f"marking {n - 2}: weight must be > 0"):
        store.add_markings("ka", bad)
    after = store.get_map("ka", with_count=True)
    assert (after.count, after.revision, after.bounds) == (1, before.revision, before.bounds)
    assert store.summary("ka").by_kind == {"unknown": 1}
    assert [m.x for m in store.iter_markings("ka")] == [pytest.approx(E0)]

    # The same markings, valid, with the widest ones in the last, short batch.
    good = [_m(float(k % 500), float(k // 500), kind="dash") for k in range(n - 1)] + [_m(-700.0, 900.0)]
    ids = store.add_markings("ka", good)
    assert len(ids) == n and len(set(ids)) == n
    info = store.get_map("ka", with_count=True)
    assert info.count == n + 1 and info.revision == before.revision + 1
    assert info.bounds == pytest.approx((E0 - 700.0, N0, E0 + 499.0, N0 + 900.0))
    assert store.summary("ka").by_kind["dash"] == n - 1
    got = store.get_marking("ka", ids[INSERT_BATCH])
    assert (got.x, got.y) == (pytest.approx(E0 + INSERT_BATCH % 500), pytest.approx(N0 + INSERT_BATCH // 500))

def test_crs_is_chosen_from_first_lonlat_import(store):
    store.create_map("anywhere")
    with pytest.raises(StoreError, match="no CRS yet"):
        store.add_markings("anywhere", [_m(0, 0)])
    m = Marking(x=math.nan, y=math.nan, lon=-104.8, lat=38.8)  # Colorado Springs
    store.add_markings("anywhere", [m], lonlat=True)
    info = store.get_map("anywhere")
    assert info.crs == "EPSG:32613"
    back = store.query_bbox("anywhere", *info.bounds)[0]
    assert back.lon == pytest.approx(-104.8, abs=1e-9) and back.lat == pytest.approx(38.8, abs=1e-9)


def test_bbox_query_matches_brute_force(store):
    store.create_map("ka", crs="EPSG:25832")
    rng = np.random.default_rng(1)
    pts = rng.uniform(-500, 500, size=(3000, 2))
    store.bulk_load("ka", (Marking(x=E0 + a, y=N0 + b) for a, b in pts))
    for _ in range(20):
        x0, y0 = rng.uniform(-520, 480, 2)
        w, h = rng.uniform(0.5, 200, 2)
        got = store.query_bbox("ka", E0 + x0, N0 + y0, E0 + x0 + w, N0 + y0 + h)
        inside = (
            (pts[:, 0] >= x0) & (pts[:, 0] <= x0 + w) & (pts[:, 1] >= y0) & (pts[:, 1] <= y0 + h)
        )
        assert len(got) == inside.sum()
        assert store.count_bbox("ka", E0 + x0, N0 + y0, E0 + x0 + w, N0 + y0 + h) == inside.sum()
        assert all(x0 <= m.x - E0 <= x0 + w and y0 <= m.y - N0 <= y0 + h for m in got)
    # paging is stable and complete
    box = (E0 - 100, N0 - 100, E0 + 100, N0 + 100)
    everything = [m.id for m in store.query_bbox("ka", *box)]
    pages = [m.id for off in range(0, len(everything), 7) for m in store.query_bbox("ka", *box, limit=7, offset=off)]
    assert pages == everything == sorted(everything)
    with pytest.raises(StoreError, match="min <= max"):
        store.query_bbox("ka", E0 + 1, N0, E0, N0 + 1)
    with pytest.raises(StoreError, match="finite"):
        store.query_bbox("ka", math.nan, N0, E0, N0 + 1)
    assert len(store.query_bbox("ka", -1e12, -1e12, 1e12, 1e12)) == len(pts)


def test_bbox_uses_the_grid_index(store):
    store.create_map("ka", crs="EPSG:25832")
    store.add_markings("ka", [_m(0, 0)])
    m = store.query_bbox("ka", E0 - 1, N0 - 1, E0 + 1, N0 + 1)[0]
    with store.engine.connect() as conn:
        gx, gy = conn.execute(text("SELECT gx, gy FROM markings WHERE id = :i"), {"i": m.id}).one()
        assert (gx, gy) == (math.floor(E0 / GRID_CELL_M), math.floor(N0 / GRID_CELL_M))
        if store.dialect == "sqlite":
            plan = " ".join(
                str(r[-1])
                for r in conn.exec_driver_sql(
                    "EXPLAIN QUERY PLAN SELECT id FROM markings WHERE map_id='ka' AND gx BETWEEN 1 AND 2 "
                    "AND gy BETWEEN 1 AND 2 AND x BETWEEN 1 AND 2 AND y BETWEEN 1 AND 2"
                )
            )
            assert "ix_markings_grid" in plan


def test_changeset_is_atomic_and_versioned(store):
    store.create_map("ka", crs="EPSG:25832")
    a, b, c = store.add_markings("ka", [_m(0, 0), _m(10, 0), _m(20, 0)])
    rev = store.map_revision("ka")
    res = store.apply_changeset(
        "ka",
        [
            Change("update", id=a, version=1, fields={"status": "rejected"}),
            Change("update", id=b, version=1, fields={"x": E0 + 11.0}),
            Change("delete", id=c, version=1),
            Change("create", marking=Marking(x=math.nan, y=math.nan, lon=8.42, lat=49.004, source="manual")),
        ],
        who="bob",
        comment="review",
    )
    assert [r["op"] for r in res.results] == ["update", "update", "delete", "create"]
    assert store.get_marking("ka", a).status == "rejected"
    moved = store.get_marking("ka", b)
    assert moved.version == 2 and moved.x == E0 + 11.0 and moved.lon != store.get_marking("ka", a).lon
    with pytest.raises(UnknownMarkingError):
        store.get_marking("ka", c)
    assert store.map_revision("ka") == rev + 1

    # A stale version anywhere rejects the whole changeset.
    before = [(m.id, m.version, m.x, m.status) for m in store.list_markings("ka")[0]]
    with pytest.raises(ConflictError) as err:
        store.apply_changeset(
            "ka",
            [
                Change("update", id=a, version=1, fields={"status": "accepted"}),  # stale
                Change("delete", id=b, version=2),  # current
                Change("delete", id=c, version=1),  # gone
            ],
            who="carol",
        )
    assert {(x.id, x.reason) for x in err.value.conflicts} == {(a, "version"), (c, "missing")}
    # An invalid value anywhere also rejects it whole.
    with pytest.raises(InvalidMarkingError, match="change 1"):
        store.apply_changeset(
            "ka",
            [Change("delete", id=b, version=2), Change("update", id=a, version=2, fields={"weight": -1})],
            who="carol",
        )
    with pytest.raises(InvalidMarkingError, match="cannot change field"):
        store.apply_changeset("ka", [Change("update", id=a, fields={"version": 9})], who="carol")
    assert [(m.id, m.version, m.x, m.status) for m in store.list_markings("ka")[0]] == before


def test_history_and_revert(store):
    store.create_map("ka", crs="EPSG:25832")
    a, b = store.add_markings("ka", [_m(0, 0), _m(10, 0)])
    cs = store.apply_changeset(
        "ka",
        [
            Change("update", id=a, version=1, fields={"status": "accepted", "bearing_deg": 45.0}),
            Change("delete", id=b, version=1),
            Change("create", marking=_m(30, 0, source="manual")),
        ],
        who="dave",
        comment="edit",
    )
    created = cs.results[2]["id"]
    edits, total = store.history("ka", changeset_id=cs.changeset_id)
    assert total == 3
    upd = next(e for e in edits if e.op == "update")
    assert upd.before["status"] == "unreviewed" and upd.after["status"] == "accepted"
    assert upd.before["version"] == 1 and upd.after["version"] == 2 and upd.who == "dave"
    assert next(e for e in edits if e.op == "delete").after is None
    one = store.get_changeset("ka", cs.changeset_id)
    assert (one.who, one.comment, one.n_create, one.n_update, one.n_delete) == ("dave", "edit", 1, 1, 1)
    assert store.get_edit("ka", upd.id) == upd
    store.create_map("other", crs="EPSG:25832")
    assert store.get_changeset("other", cs.changeset_id) is None  # ids are per map
    assert store.get_edit("other", upd.id) is None
    with pytest.raises(UnknownMapError):
        store.get_edit("nope", upd.id)

    rv = store.revert_changeset("ka", cs.changeset_id, who="erin")
    restored = store.get_marking("ka", a)
    assert restored.status == "unreviewed" and restored.bearing_deg == 0.0 and restored.version == 3
    again = store.get_marking("ka", b)  # re-created with its id; its version moved on
    assert again.x == E0 + 10 and again.version == 2
    with pytest.raises(UnknownMarkingError):
        store.get_marking("ka", created)
    infos, n = store.changesets("ka")
    assert infos[0].id == rv.changeset_id and infos[0].reverts == cs.changeset_id and n == 3
    # Reverting again conflicts: the markings changed since that changeset, and
    # the deleted one exists again.
    with pytest.raises(ConflictError):
        store.revert_changeset("ka", cs.changeset_id, who="erin")
    only_delete = store.apply_changeset("ka", [Change("delete", id=b)], who="f")
    store.revert_changeset("ka", only_delete.changeset_id, who="f")
    with pytest.raises(ConflictError) as err:
        store.revert_changeset("ka", only_delete.changeset_id, who="f")
    assert [(c.id, c.reason) for c in err.value.conflicts] == [(b, "exists")]


def test_a_revert_of_updates_restores_every_field_of_every_marking(store):
    """A changeset of updates alone (what a review or a bulk edit makes) is reverted by restoring
    the states its log holds: positions (and lon/lat, and where a box finds them), every other
    field and ``extra`` come back exactly, versions move on, and the revert is logged as edits
    whose ``before`` is the state it undid. A marking changed since is a conflict, and then
    nothing is written."""
    store.create_map("ka", crs="EPSG:25832")
    ids = store.add_markings("ka", [_m(10.0 * k, 0.0, source="detected", score=0.1 * k, kind="dash",
                                       bearing_deg=5.0 * k, extra={"k": k}) for k in range(6)])  # fmt: skip
    original = {m.id: m for m in store.iter_markings("ka")}
    lon, lat = __import__("mapbuilder.crs", fromlist=["to_wgs84"]).to_wgs84("EPSG:25832").transform(E0 + 900, N0)
    edit = store.apply_changeset("ka", [
        Change("update", id=ids[0], fields={"lon": lon, "lat": lat}),
        Change("update", id=ids[1], fields={"status": "accepted", "extra": {"note": "checked"}}),
        Change("update", id=ids[2], fields={"kind": "stop_line", "score": None, "bearing_deg": 90.0}),
        Change("update", id=ids[3], fields={"x": E0 + 33.0, "y": N0 + 4.0, "length_m": 0.5, "weight": 2.0}),
    ], who="ann")  # fmt: skip
    rev = store.get_map("ka").revision
    back = store.revert_changeset("ka", edit.changeset_id, who="bob")
    now = {m.id: m for m in store.iter_markings("ka")}
    for i in ids:
        a, b = now[i], original[i]
        assert (a.version, b.version) == ((3, 1) if i in ids[:4] else (1, 1))
        assert back.markings.get(i, a) == a
        a.version = b.version
        assert a == b
    assert [r["version"] for r in back.results] == [3, 3, 3, 3]
    near = store.query_bbox("ka", E0 - 1, N0 - 1, E0 + 1, N0 + 1)
    assert [m.id for m in near] == [ids[0]]  # found where it was, not where it had been moved
    assert store.query_bbox("ka", E0 + 899, N0 - 1, E0 + 901, N0 + 1) == []
    log, n = store.history("ka", changeset_id=back.changeset_id)
    assert n == 4
    done = {e.marking_id: e for e in store.history("ka", changeset_id=edit.changeset_id)[0]}
    for e in log:
        assert e.before == done[e.marking_id].after and e.who == "bob"
        assert e.after == {**done[e.marking_id].before, "version": 3}
    assert sorted(m.id for _, m in store.changes("ka", rev).changed) == sorted(ids[:4])
    assert store.get_changeset("ka", back.changeset_id).reverts == edit.changeset_id

    # changed since, or deleted since: conflicts, and nothing is written
    again = store.apply_changeset("ka", [Change("update", id=i, fields={"status": "rejected"}) for i in ids[:3]],
                                  who="ann")  # fmt: skip
    store.apply_changeset("ka", [Change("update", id=ids[1], fields={"status": "accepted"}),
                                 Change("delete", id=ids[2])], who="cy")  # fmt: skip
    rev, state = store.get_map("ka").revision, {m.id: m for m in store.iter_markings("ka")}
    with pytest.raises(ConflictError) as err:
        store.revert_changeset("ka", again.changeset_id, who="bob")
    assert sorted((c.id, c.reason, c.expected_version, c.actual_version) for c in err.value.conflicts) == [
        (ids[1], "version", 4, 5), (ids[2], "missing", 4, None)]  # fmt: skip
    assert store.get_map("ka").revision == rev and {m.id: m for m in store.iter_markings("ka")} == state


def _sqlite_plans(store: Store, call, table: str) -> list[list[str]]:
    """SQLite's plan (EXPLAIN QUERY PLAN) of every SELECT of ``table`` that ``call()`` runs."""
    from sqlalchemy import event

    plans = []

    def _plan(conn, cursor, statement, parameters, context, executemany):
        if not executemany and statement.lstrip().upper().startswith("SELECT") and f"FROM {table}" in statement:
            plans.append([r[-1] for r in cursor.connection.execute("EXPLAIN QUERY PLAN " + statement,
                                                                   parameters).fetchall()])  # fmt: skip

    event.listen(store.engine, "before_cursor_execute", _plan)
    try:
        call()
    finally:
        event.remove(store.engine, "before_cursor_execute", _plan)
    return plans


def test_sqlite_reads_markings_through_the_index_each_read_needs(sqlite_url):
    """SQLite keeps no statistics, so its planner picks an index by the shape of a query. Each
    read of a city's map goes through the index that answers it without reading the rest of
    the map: a changeset's markings by their ids (with the map's id beside a list of five or
    more, SQLite walked the whole map once per statement: 127 ms for a changeset of 20 updates
    among 1,000,000); a page of the map, and an export, in id order (it sorted the whole map
    for every page); a box through the grid (ordered by id, SQLite would walk the map in id
    order and test each marking against the box); one marking's history through its own
    index (it scanned the map's edit log). PostgreSQL plans by its statistics."""
    store = Store(sqlite_url)
    store.create_map("ka", crs="EPSG:25832")
    ids = store.add_markings("ka", [_m(float(k), 0.0) for k in range(40)])
    grid = "SEARCH markings USING INDEX ix_markings_grid (map_id=? AND gx=? AND gy>? AND gy<?)"

    def edit():
        cs = store.apply_changeset("ka", [Change("update", id=i, fields={"status": "accepted"}) for i in ids],
                                   who="t")  # fmt: skip
        store.revert_changeset("ka", cs.changeset_id, who="t")

    plans = [p for p in _sqlite_plans(store, edit, "markings") if "INTEGER PRIMARY KEY" in " ".join(p) or
             "ix_markings" in " ".join(p)]  # fmt: skip
    assert plans == [["SEARCH markings USING INTEGER PRIMARY KEY (rowid=?)"]] * 2
    by_id = ["SEARCH markings USING INDEX ix_markings_map (map_id=? AND id>?)"]
    assert _sqlite_plans(store, lambda: list(store.iter_markings("ka", batch=10)), "markings") == [by_id] * 5
    assert _sqlite_plans(store, lambda: store.list_markings("ka", offset=10), "markings")[-1] == [
        "SEARCH markings USING INDEX ix_markings_map (map_id=?)"]  # fmt: skip
    w, s_, e, n = store.get_map("ka").bounds_wgs84()  # a box reaching past the map reads the map whole
    box = (w, s_, w + (e - w) * 0.04, n)  # two markings of 40: through the grid
    assert _sqlite_plans(store, lambda: list(store.iter_markings("ka", lonlat_box=box)), "markings") == [
        [grid, "USE TEMP B-TREE FOR ORDER BY"]] * 2  # fmt: skip
    assert _sqlite_plans(store, lambda: store.query_lonlat_box("ka", box), "markings")[-1] == [
        grid, "USE TEMP B-TREE FOR ORDER BY"]  # fmt: skip
    box = (w, s_, w + (e - w) * 0.06, n)  # three of 40, past WIDE_BOX_SHARE: through the ids in order
    assert _sqlite_plans(store, lambda: list(store.iter_markings("ka", lonlat_box=box)), "markings") == [by_id] * 2
    assert _sqlite_plans(store, lambda: store.query_lonlat_box("ka", box, offset=1), "markings")[-1] == [
        "SEARCH markings USING INDEX ix_markings_map (map_id=?)"]  # fmt: skip
    assert [m.id for m in store.query_lonlat_box("ka", box, offset=1)[0]] == ids[1:3]
    assert _sqlite_plans(store, lambda: store.query_bbox("ka", E0, N0, E0 + 9, N0 + 1), "markings") == [
        [grid, "USE TEMP B-TREE FOR ORDER BY"]]  # fmt: skip
    assert [m.id for m in store.query_bbox("ka", E0 + 2.5, N0 - 1, E0 + 5.5, N0 + 1)] == ids[3:6]
    assert [m.id for m in store.iter_markings("ka", batch=7)] == ids
    assert _sqlite_plans(store, lambda: store.history("ka", marking_id=ids[3]), "edits") == [
        ["SEARCH edits USING COVERING INDEX ix_edits_marking (map_id=? AND marking_id=?)"],
        ["SEARCH edits USING INDEX ix_edits_marking (map_id=? AND marking_id=?)"]]  # fmt: skip


def test_deleted_ids_are_never_reused(store):
    store.create_map("ka", crs="EPSG:25832")
    (a,) = store.add_markings("ka", [_m(0, 0)])
    store.apply_changeset("ka", [Change("delete", id=a)], who="x")
    (b,) = store.add_markings("ka", [_m(0, 0)])
    assert b > a


def test_replace_detected_keeps_what_people_decided(store):
    store.create_map("ka", crs="EPSG:25832")
    job = store.create_job("build", "ka", {"image": "x.tif"})
    first = [_m(0, 0), _m(10, 0), _m(20, 0), _m(30, 0)]
    assert store.replace_detected("ka", "t0", first, job_id=job) == 4
    ids = [m.id for m in store.list_markings("ka")[0]]
    # A person rejects one, moves another (accepted), and adds one by hand.
    store.apply_changeset(
        "ka",
        [
            Change("update", id=ids[0], fields={"status": "rejected"}),
            Change("update", id=ids[1], fields={"status": "accepted", "x": E0 + 10.2}),
            Change("create", marking=_m(40, 0, source="manual")),
        ],
        who="p",
    )
    # The rebuild detects the same four again plus the hand-added one.
    again = [_m(0.1, 0), _m(10, 0.05), _m(20, 0), _m(30.02, 0), _m(40.1, 0)]
    inserted = store.replace_detected("ka", "t0", again, job_id=job)
    assert inserted == 2  # near the rejected, moved and manual ones: suppressed
    got = sorted((m.x - E0, m.source, m.status) for m in store.list_markings("ka")[0])
    assert got == [
        (0.0, "detected", "rejected"),
        (pytest.approx(10.2), "detected", "accepted"),
        (20.0, "detected", "unreviewed"),
        (pytest.approx(30.02), "detected", "unreviewed"),
        (40.0, "manual", "unreviewed"),
    ]
    # Another tile is untouched by this tile's replacement.
    store.replace_detected("ka", "t1", [_m(500, 0)], job_id=job)
    store.replace_detected("ka", "t0", [], job_id=None)
    assert _count(store, "ka") == 4  # t0's two unreviewed detections went, t1's stays
    assert store.done_tiles(job) == {"t0", "t1"}


def test_the_ground_a_build_imaged_is_kept_per_tile_beyond_its_job(store):
    """Each tile's ground is recorded with its detections, in the same transaction; a rebuilt tile
    replaces its own, an empty replacement (a stale tile dropped) keeps it, and the map's footprint
    is the union of its tiles', whichever job built them."""
    import shapely

    store.create_map("ka", crs="EPSG:25832")
    assert store.imaged_footprint("ka") is None
    rev = store.map_head("ka")[0]
    west = shapely.box(E0, N0, E0 + 100, N0 + 100)
    east = shapely.box(E0 + 100, N0, E0 + 200, N0 + 100)
    job = store.create_job("build", "ka", {"image": "a.tif"})
    store.replace_detected("ka", "a/t0", [_m(10, 10)], job_id=job, ground=shapely.to_wkb(west))
    store.replace_detected("ka", "a/t1", [_m(110, 10)], job_id=job, ground=shapely.to_wkb(east))
    assert store.map_head("ka")[0] > rev  # an index drawn before knows it is stale
    assert store.imaged_footprint("ka").equals(shapely.box(E0, N0, E0 + 200, N0 + 100))
    # a rebuild of t1 by another job imaged less of it (nodata): its own ground is replaced
    again = store.create_job("build", "ka", {"image": "a.tif", "again": True})
    store.replace_detected("ka", "a/t1", [_m(110, 10)], job_id=again,
                           ground=shapely.to_wkb(shapely.box(E0 + 100, N0, E0 + 150, N0 + 100)))
    store.replace_detected("ka", "a/t0", [], job_id=None)  # dropped as stale: the ground was imaged
    assert store.imaged_footprint("ka").equals(shapely.box(E0, N0, E0 + 150, N0 + 100))
    store.create_map("other", crs="EPSG:25832")
    assert store.imaged_footprint("other") is None
    with pytest.raises(UnknownMapError):
        store.imaged_footprint("nowhere")
    # a tile whose ground could not be written (a marking out of range) writes neither
    with pytest.raises(InvalidMarkingError):
        store.replace_detected("ka", "a/t2", [Marking(x=E0 + 300, y=N0, weight=-1.0)], job_id=job,
                               ground=shapely.to_wkb(shapely.box(E0 + 200, N0, E0 + 300, N0 + 100)))
    assert store.imaged_footprint("ka").equals(shapely.box(E0, N0, E0 + 150, N0 + 100))
    with pytest.raises(StoreError, match="not WKB"):
        store.replace_detected("ka", "a/t0", [_m(10, 10)], job_id=job, ground=b"not a polygon")
    assert store.imaged_footprint("ka").equals(shapely.box(E0, N0, E0 + 150, N0 + 100))
    store.delete_map("ka")
    store.create_map("ka", crs="EPSG:25832")
    assert store.imaged_footprint("ka") is None


def test_summary_counts_what_the_map_holds_and_its_review(store):
    """``Store.summary``: counts by status, source and kind equal a count of the markings one by
    one; the detections' review and their scores' histogram follow accepts and rejects."""
    store.create_map("ka", crs="EPSG:25832")
    rng = np.random.default_rng(5)
    scores = [0.0, 0.05, 0.1, 0.35, 0.999, 1.0, *rng.uniform(0, 1, 30).round(3)]
    ms = [_m(2.0 * k, 0.0, source="detected", score=float(v), kind="dash" if k % 4 == 0 else None)
          for k, v in enumerate(scores)]  # fmt: skip
    ms += [_m(2.0 * k, 10.0, source="detected", score=None) for k in range(3)]  # a detection without a score
    ms += [_m(2.0 * k, 20.0, source="imported", kind="stop_line", status="accepted") for k in range(4)]
    ids = store.add_markings("ka", ms)
    det = ids[: len(scores)]
    store.apply_changeset("ka", [Change("update", id=det[0], fields={"status": "accepted"}),
                                 Change("update", id=det[1], fields={"status": "rejected"}),
                                 Change("delete", id=det[2])], who="t")  # fmt: skip
    sm = store.summary("ka")
    held = list(store.iter_markings("ka"))

    def tally(key):
        out = {}
        for m in held:
            out[key(m)] = out.get(key(m), 0) + 1
        return dict(sorted(out.items()))

    assert sm.count == len(held) == len(ms) - 1 and sm.revision == store.get_map("ka").revision
    assert sm.by_status == tally(lambda m: m.status) and sm.by_source == tally(lambda m: m.source)
    assert sm.by_kind == tally(lambda m: m.kind or "unknown")
    assert sm.detections == {"unreviewed": len(scores) - 3 + 3, "accepted": 1, "rejected": 1}
    assert sm.reviewed_share == pytest.approx(2 / (len(scores) - 1 + 3))
    left = [m.score for m in held if m.source == "detected" and m.status == "unreviewed" and m.score is not None]
    assert sm.unreviewed_scores == [sum(min(int(v * 10), 9) == k for v in left) for k in range(10)]
    assert sm.unreviewed_scores[9] >= 2  # 0.999 and 1.0 in the last bin
    with pytest.raises(UnknownMapError):
        store.summary("nope")
    store.create_map("empty", crs="EPSG:25832")
    empty = store.summary("empty")
    assert (empty.count, empty.reviewed_share, sum(empty.unreviewed_scores)) == (0, None, 0)


def _summary_as_counted(store: Store, map_id: str):
    """The map's summary from its kept counts, beside the one counted from its markings (a box
    just around the map: one reaching past it is read as the whole map, from its counts)."""
    box = store.get_map(map_id).bounds_wgs84() or (-180.0, -90.0, 180.0, 90.0)
    return store.summary(map_id), store.summary(map_id, lonlat_box=box)


def test_the_kept_counts_follow_every_kind_of_write(store):
    """The whole map's summary is read from counts that every write keeps in its transaction:
    after an import, a bulk load, creates, updates and deletes, a review by score, reverts of
    each (a deleted marking back under its id), a rebuilt tile, a failed changeset and a map
    made anew, they equal a count of the markings themselves."""
    store.create_map("ka", crs="EPSG:25832")
    rng = np.random.default_rng(8)
    steps = []

    def check(what):
        kept, whole = _summary_as_counted(store, "ka")
        assert kept == whole, what
        held = list(store.iter_markings("ka"))
        for statuses in (["accepted"], ["unreviewed", "rejected"]):
            n = sum(m.status in statuses for m in held)
            assert store.count_markings("ka", statuses) == store.list_markings("ka", 1, statuses=statuses)[1] == n
        queue = sum(m.status == "unreviewed" and m.source == "detected" for m in held)
        assert store.review_queue("ka", limit=1)[1] == queue, what
        steps.append(what)

    scores = [None, -0.5, 0.0, 0.1, 0.3, 0.7, 0.9, 0.95, 1.0, 1.5, *rng.uniform(0, 1, 20).round(3)]
    ids = store.add_markings("ka", [_m(2.0 * k, 0.0, source="detected", score=v, kind=("dash", None, "solid")[k % 3])
                                    for k, v in enumerate(scores)])  # fmt: skip
    check("import")
    # a box just around the map holds its every marking, those at its edges too
    assert store.count_markings("ka", lonlat_box=store.get_map("ka").bounds_wgs84()) == len(scores)
    store.bulk_load("ka", (_m(2.0 * k, 5.0, source="imported", kind="stop_line", status="accepted")
                           for k in range(7)))  # fmt: skip
    check("bulk load")
    cs = store.apply_changeset("ka", [
        Change("update", id=ids[3], fields={"status": "accepted"}),
        Change("update", id=ids[4], fields={"score": 0.05, "kind": "stop_line"}),
        Change("update", id=ids[5], fields={"source": "manual", "x": E0 + 77.0}),
        Change("delete", id=ids[6]),
        Change("create", marking=_m(50.0, 50.0, source="manual", score=0.42)),
    ], who="t")  # fmt: skip
    check("changeset")
    with pytest.raises(ConflictError):
        store.apply_changeset("ka", [Change("update", id=ids[7], fields={"status": "rejected"}),
                                     Change("delete", id=ids[6])], who="t")  # fmt: skip
    check("a changeset refused")
    store.revert_changeset("ka", cs.changeset_id, who="t")
    check("revert of creates, updates and deletes")
    review = store.review_by_score("ka", accept_from=0.8, reject_below=0.2, who="t")
    assert review.accepted and review.rejected
    check("review by score")
    store.revert_changeset("ka", review.changeset_id, who="t")
    check("revert of updates alone")
    store.apply_changeset("ka", [Change("update", id=i, fields={"tile_key": "t1"}) for i in ids[:12]], who="t")
    n = store.replace_detected("ka", "t1", [_m(3.0 * k, 30.0, score=0.61, kind="dash") for k in range(5)])
    assert n == 5
    check("rebuilt tile")
    store.delete_map("ka")
    store.create_map("ka", crs="EPSG:25832")
    check("made anew")
    assert store.summary("ka").count == 0 and len(steps) == 9


def test_a_box_holding_the_whole_map_reads_the_map_whole(store):
    """A box that holds the whole map (a client zoomed out past it) gives what the map gives
    without a box: its pages in id order with the map's count, its iteration, its count and its
    summary, read without a box (on SQLite, in the index order of its ids); a box just around
    the map still holds every marking, read through the grid."""
    store.create_map("ka", crs="EPSG:25832")
    rng = np.random.default_rng(4)
    ids = store.add_markings("ka", [_m(a, b, source="detected", score=float(v), status=st)
                                    for (a, b), v, st in zip(rng.uniform(0, 900, (60, 2)), rng.uniform(0, 1, 60),
                                                              ["unreviewed", "accepted", "rejected"] * 20)])  # fmt: skip
    world = (-180.0, -90.0, 180.0, 90.0)
    w, s_, e, n = store.get_map("ka").bounds_wgs84()
    around = (w - 1e-4, s_ - 1e-4, e + 1e-4, n + 1e-4)
    for box in (world, around, (w, s_, e, n)):
        page, total = store.query_lonlat_box("ka", box, limit=7, offset=14)
        assert ([m.id for m in page], total) == (ids[14:21], 60)
        assert store.query_lonlat_box("ka", box, statuses=["accepted"], limit=100)[1] == 20
        assert [m.id for m in store.iter_markings("ka", batch=9, lonlat_box=box)] == ids
        assert store.count_markings("ka", ["rejected"], lonlat_box=box) == 20
        assert store.summary("ka", lonlat_box=box) == store.summary("ka")
        assert store.review_queue("ka", lonlat_box=box) == store.review_queue("ka")
    if store.dialect == "sqlite":
        for box in (around, (w, s_, e, n)):  # read whole; walked in id order, each marking tested
            page_plan = _sqlite_plans(store, lambda: store.query_lonlat_box("ka", box, limit=7), "markings")[-1]
            assert page_plan == ["SEARCH markings USING INDEX ix_markings_map (map_id=?)"]
    half = (w, s_, (w + e) / 2, n)
    inside = [m.id for m in store.iter_markings("ka") if m.lon <= (w + e) / 2]
    assert 0 < len(inside) < 60 and [m.id for m in store.iter_markings("ka", lonlat_box=half)] == inside
    assert store.summary("ka", lonlat_box=half).count == len(inside)


def test_a_wide_box_reads_what_the_grid_reads(store):
    """A box over ``WIDE_BOX_SHARE`` of the map or more is read by walking the map's ids in
    order, a narrower one through the grid: both give exactly the markings whose stored lon/lat
    lie in the box, in id order, the same pages, counts, summaries and review queue, at a map's
    edge and across a box's corners."""
    from mapbuilder.store import WIDE_BOX_SHARE

    store.create_map("ka", crs="EPSG:25832")
    rng = np.random.default_rng(8)
    n = 400
    xy = rng.uniform(0, 2000, (n, 2))
    xy[:40, 1] = rng.uniform(0, 30, 40)  # a dense strip: a box's share of the area is not of the markings
    ids = store.add_markings("ka", [_m(a, b, source="detected", score=float(v), status=st, kind=k)
                                    for (a, b), v, st, k in zip(xy, rng.uniform(0, 1, n),
                                                                ["unreviewed", "accepted", "rejected", "unreviewed"] * 100,
                                                                ["dash", None] * 200)])  # fmt: skip
    every = list(store.iter_markings("ka"))
    assert [m.id for m in every] == ids
    w, s_, e, n_ = store.get_map("ka").bounds_wgs84()
    dx, dy = e - w, n_ - s_
    boxes = [(w + dx * a, s_ + dy * b, w + dx * c, s_ + dy * d) for a, b, c, d in (
        (0.4, 0.4, 0.5, 0.5), (0.0, 0.0, 0.2, 0.2), (0.1, -0.5, 0.9, 0.03),  # 1 %, 4 %, 2.4 %: grid
        (0.3, 0.3, 0.6, 0.6), (-0.2, -0.2, 0.5, 0.99), (0.0, 0.0, 1.0, 0.5),  # 9 %, 50 %, 50 %: ids
        (0.01, 0.01, 0.99, 0.99), (0.2, 0.2, 0.2 + 0.2237, 0.2 + 0.2237))]  # fmt: skip
    shares = [store._box_share(store.get_map("ka").bounds_wgs84(), b) for b in boxes]
    assert sum(sh < WIDE_BOX_SHARE for sh in shares) == 3 and sum(sh >= WIDE_BOX_SHARE for sh in shares) == 5
    for box in boxes:
        inside = [m for m in every if box[0] <= m.lon <= box[2] and box[1] <= m.lat <= box[3]]
        want = [m.id for m in inside]
        assert want, box
        page, total = store.query_lonlat_box("ka", box, limit=9, offset=3)
        assert ([m.id for m in page], total) == (want[3:12], len(want))
        assert [m.id for m in store.iter_markings("ka", batch=7, lonlat_box=box)] == want
        acc = [m.id for m in inside if m.status == "accepted"]
        assert store.query_lonlat_box("ka", box, statuses=["accepted"], limit=500)[0] == \
            [m for m in inside if m.status == "accepted"] and len(acc) == store.count_markings("ka", ["accepted"], box)
        summary = store.summary("ka", lonlat_box=box)
        assert summary.count == len(want) and summary.by_kind.get("dash", 0) == sum(m.kind == "dash" for m in inside)
        queue = sorted((m for m in inside if m.status == "unreviewed"), key=lambda m: (m.score, m.id))
        assert [m.id for m in store.review_queue("ka", lonlat_box=box, limit=1000)[0]] == [m.id for m in queue]
    assert len({len(store.query_lonlat_box("ka", b, limit=1)[0]) for b in boxes}) == 1  # each box holds markings


def test_the_review_queue_is_read_in_the_order_of_its_index(store):
    """A whole map's review queue is read through ``ix_markings_queue``, a partial index of its
    unreviewed detections by (score, id): every page, from any key, in any size, gives what a
    sort of the queue gives (ties by id, negative scores first, those without a score last, a
    page reaching across from the scored ones to the rest), and on SQLite no page sorts."""
    store.create_map("ka", crs="EPSG:25832")
    rng = np.random.default_rng(5)
    scores = [None if k % 7 == 0 else float(v) for k, v in enumerate(rng.choice([-0.5, 0.1, 0.25, 0.5, 0.9], 60))]
    ms = [_m(float(k), 0.0, source=("manual" if k % 11 == 3 else "detected"),
             status=("accepted" if k % 13 == 5 else "unreviewed"), score=v) for k, v in enumerate(scores)]  # fmt: skip
    ids = store.add_markings("ka", ms)
    queue = sorted((i for i, m in zip(ids, ms) if m.source == "detected" and m.status == "unreviewed"),
                   key=lambda i: (scores[ids.index(i)] is None, scores[ids.index(i)] or 0.0, i))  # fmt: skip
    assert 40 < len(queue) < 60 and scores[ids.index(queue[-1])] is None
    for size in (1, 4, 7, 100):
        got, after = [], None
        while True:
            page, total = store.review_queue("ka", after=after, limit=size)
            assert total == len(queue) and len(page) <= size
            if not page:
                break
            got += [m.id for m in page]
            after = (page[-1].score, page[-1].id)
        assert got == queue, size
    # A box's queue: a wide one walked along the queue, a narrow one read through the grid.
    from mapbuilder.store import WIDE_BOX_SHARE

    by_id = {m.id: m for m in store.iter_markings("ka")}
    w, s_, e, n_ = store.get_map("ka").bounds_wgs84()
    wide, narrow = (w + (e - w) * 0.15, s_ - 1e-5, w + (e - w) * 0.7, n_ + 1e-5), \
        (w + (e - w) * 0.3, s_ - 1e-5, w + (e - w) * 0.345, n_ + 1e-5)  # fmt: skip
    for box, is_wide in ((wide, True), (narrow, False)):
        assert (store._box_share(store.get_map("ka").bounds_wgs84(), box) >= WIDE_BOX_SHARE) is is_wide
        inside = [i for i in queue if box[0] <= by_id[i].lon <= box[2]]
        assert 1 < len(inside) < len(queue)
        for size in (1, 3, 100):
            got, after = [], None
            while True:
                page, total = store.review_queue("ka", after=after, limit=size, lonlat_box=box)
                assert total == len(inside) and len(page) <= size
                if not page:
                    break
                got += [m.id for m in page]
                after = (page[-1].score, page[-1].id)
            assert got == inside, (box, size)
    if store.dialect == "sqlite":
        key = (scores[ids.index(queue[10])], queue[10])
        for box in (None, wide):
            plans = _sqlite_plans(store, lambda: store.review_queue("ka", after=key, limit=100, lonlat_box=box),
                                  "markings")  # fmt: skip
            plans = [p for p in plans if "ix_markings_queue" in " ".join(p)]
            assert plans == [["SEARCH markings USING INDEX ix_markings_queue (map_id=? AND score>?)"],
                             ["SEARCH markings USING INDEX ix_markings_queue (map_id=? AND score=?)"]], (box, plans)


def test_a_large_load_has_postgresql_count_the_table(postgres_url):
    """After a load of ``ANALYZE_FROM`` markings or more PostgreSQL's statistics count them (it
    plans a box's read by them), without waiting for autovacuum; a small load leaves that to it."""
    from mapbuilder.store import ANALYZE_FROM

    store = Store(postgres_url)
    store.create_map("ka", crs="EPSG:25832")

    def analyzed():
        with store.engine.connect() as conn:
            return conn.exec_driver_sql("SELECT reltuples FROM pg_class WHERE relname = 'markings'").scalar()

    store.add_markings("ka", [_m(float(k), 0.0) for k in range(10)])
    assert analyzed() <= 0  # never counted (-1 on PostgreSQL 14 and later)
    rng = np.random.default_rng(2)
    store.bulk_load("ka", (_m(a, b) for a, b in rng.uniform(0, 3000, (ANALYZE_FROM, 2))))
    assert analyzed() == ANALYZE_FROM + 10
    store.close()


def test_an_upgrade_counts_the_markings_stored_before(db_url):
    """Schema revision 0007 counts the markings a database held before it, as the writes since
    keep them."""
    old = Store(db_url, upgrade=False)
    old.upgrade("0006")
    rows = [("detected", "unreviewed", None, None), ("detected", "unreviewed", 0.3, "dash"),
            ("detected", "unreviewed", 0.95, "dash"), ("detected", "unreviewed", 0.95, "dash"),
            ("detected", "accepted", 0.5, None), ("manual", "accepted", -1.0, "solid"),
            ("imported", "rejected", 1.2, None), ("detected", "unreviewed", 0.1, None)]  # fmt: skip
    with old.engine.begin() as conn:
        conn.execute(text("INSERT INTO maps (id, title, crs, revision, feed_since, created_at, updated_at) "
                          "VALUES ('old', '', 'EPSG:25832', 1, 0, CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"))
        for k, (source, status, score, kind) in enumerate(rows):
            conn.execute(text(
                "INSERT INTO markings (map_id, gx, gy, x, y, lon, lat, weight, length_m, width_m, bearing_deg, "
                "score, kind, source, status, extra, version, revision, created_at, updated_at) VALUES ('old', 0, 0, "
                f"{E0 + k}, {N0}, 8.4, 49.0, 1, 1, 0.1, 0, :score, :kind, :source, :status, '{{}}', 1, 1, "
                "CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"), dict(score=score, kind=kind, source=source, status=status))
    old.close()
    up = Store(db_url, upgrade=False)
    assert up.upgrade() == ("0006", migrate.head_revision())
    up.close()
    store = Store(db_url)
    kept = store.summary("old")
    assert kept.count == len(rows) and kept.unreviewed_scores == [0, 1, 0, 1, 0, 0, 0, 0, 0, 2]
    assert kept.by_kind == {"dash": 3, "solid": 1, "unknown": 4}
    assert kept.by_status == {"accepted": 2, "rejected": 1, "unreviewed": 5}
    assert kept.by_source == {"detected": 6, "imported": 1, "manual": 1}
    assert kept.detections == {"unreviewed": 5, "accepted": 1, "rejected": 0}
    # and the writes since keep them
    mid = next(m.id for m in store.iter_markings("old") if m.score == 0.3)
    store.apply_changeset("old", [Change("update", id=mid, fields={"status": "rejected"})], who="t")
    kept = store.summary("old")
    assert kept.unreviewed_scores == [0, 1, 0, 0, 0, 0, 0, 0, 0, 2] and kept.detections["rejected"] == 1
    store.close()


def test_review_by_score_decides_the_sure_detections_in_one_revertible_changeset(store):
    """``review_by_score``: the unreviewed detections at or above ``accept_from`` are accepted and
    those below ``reject_below`` rejected, in one changeset that a revert undoes; people's
    decisions, markings of other sources and detections without a score stay as they are."""
    store.create_map("ka", crs="EPSG:25832")
    scores = [0.05, 0.1, 0.15, 0.5, 0.85, 0.9, 0.95, 1.0]
    det = store.add_markings("ka", [_m(3.0 * k, 0.0, source="detected", score=s) for k, s in enumerate(scores)])
    decided = store.add_markings("ka", [_m(0.0, 5.0, source="detected", score=0.99, status="rejected"),
                                        _m(3.0, 5.0, source="detected", score=0.01, status="accepted")])  # fmt: skip
    others = store.add_markings("ka", [_m(0.0, 10.0, source="manual", score=0.01),
                                       _m(3.0, 10.0, source="detected", score=None)])  # fmt: skip
    far = store.add_markings("ka", [_m(5000.0, 0.0, source="detected", score=0.97)])
    before = {m.id: (m.status, m.version) for m in store.iter_markings("ka")}
    rev0 = store.get_map("ka").revision
    with pytest.raises(StoreError, match="give accept_from"):
        store.review_by_score("ka", who="t")
    with pytest.raises(StoreError, match="above accept_from"):
        store.review_by_score("ka", accept_from=0.5, reject_below=0.6, who="t")
    with pytest.raises(StoreError, match=r"in \[0, 1\]"):
        store.review_by_score("ka", accept_from=1.5, who="t")
    dry = store.review_by_score("ka", accept_from=0.9, reject_below=0.15, who="t", dry_run=True)
    assert (dry.accepted, dry.rejected, dry.changeset_id, dry.revision) == (4, 2, None, rev0)
    assert {m.id: (m.status, m.version) for m in store.iter_markings("ka")} == before
    # only near the first detections: the far one stays unreviewed
    to_wgs = __import__("mapbuilder.crs", fromlist=["to_wgs84"]).to_wgs84("EPSG:25832")
    w, s_ = to_wgs.transform(E0 - 10, N0 - 10)
    e, n = to_wgs.transform(E0 + 100, N0 + 100)
    res = store.review_by_score("ka", accept_from=0.9, reject_below=0.15, lonlat_box=(w, s_, e, n), who="alice")
    assert (res.accepted, res.rejected, res.revision) == (3, 2, rev0 + 1)
    now = {m.id: m for m in store.iter_markings("ka")}
    assert [now[i].status for i in det] == ["rejected", "rejected", "unreviewed", "unreviewed", "unreviewed",
                                            "accepted", "accepted", "accepted"]  # fmt: skip
    assert all(now[i].version == 2 for i, sc in zip(det, scores) if sc >= 0.9 or sc < 0.15)
    assert now[far[0]].status == "unreviewed"
    assert all((now[i].status, now[i].version) == before[i] for i in decided + others)
    cs = store.get_changeset("ka", res.changeset_id)
    assert (cs.who, cs.n_update, cs.comment) == ("alice", 5, "review by score: accept from 0.9, reject below 0.15")
    assert {r for r, _ in store.changes("ka", rev0).changed} == {rev0 + 1}
    # the revert puts every one of them back
    store.revert_changeset("ka", res.changeset_id, who="alice")
    assert {m.id: m.status for m in store.iter_markings("ka")} == {i: st for i, (st, _) in before.items()}
    none = store.review_by_score("ka", accept_from=0.999, lonlat_box=(w, s_, w + 1e-6, s_ + 1e-6), who="t")
    assert (none.accepted, none.rejected, none.changeset_id) == (0, 0, None)


def test_a_changeset_past_the_drivers_parameter_limit_is_reverted_whole(store):
    """A review of a city's detections, and its revert, name more markings than one statement may
    take parameters: PostgreSQL takes 65,535, SQLite as built here 250,000 and before 3.32 999 (set
    so here, as such a build would have it). The revert puts every marking back all the same."""
    if store.dialect == "sqlite":
        import sqlite3

        from sqlalchemy import event

        @event.listens_for(store.engine, "connect")
        def _old_limit(dbapi_conn, _):
            dbapi_conn.setlimit(sqlite3.SQLITE_LIMIT_VARIABLE_NUMBER, 999)

        store.engine.dispose()
        n = 2_500
    else:
        n = 66_000
    store.create_map("ka", crs="EPSG:25832")
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 3000, (n, 2))
    store.bulk_load("ka", (_m(a, b, source="detected", score=0.5) for a, b in xy))
    res = store.review_by_score("ka", accept_from=0.2, who="t")
    assert (res.accepted, res.rejected) == (n, 0)
    back = store.revert_changeset("ka", res.changeset_id, who="t")
    assert len(back.results) == n
    now = store.marking_arrays("ka", ["unreviewed"])
    assert len(now) == n and store.summary("ka").by_status == {"unreviewed": n}
    assert {m.version for m in store.iter_markings("ka")} == {3}
    assert store.count_changes("ka", res.revision) == n


def test_counts_follow_writes_made_by_another_store(store):
    """A map's counts follow every write, another process's too (here another Store on the
    same database), and a map made anew starts from none."""
    store.create_map("ka", crs="EPSG:25832")
    store.add_markings("ka", [_m(3.0 * k, 0.0) for k in range(4)])
    assert _count(store, "ka") == 4 and [m.count for m in store.list_maps()] == [4]
    other = Store(store.url)
    ids = other.add_markings("ka", [_m(3.0 * k, 9.0) for k in range(3)])
    other.apply_changeset("ka", [Change("delete", id=ids[0])], who="t")
    assert _count(store, "ka") == 6 and [m.count for m in store.list_maps()] == [6]
    assert store.list_markings("ka", limit=2)[1] == 6 and store.list_markings("ka", statuses=["accepted"])[1] == 0
    other.apply_changeset("ka", [Change("update", id=ids[1], fields={"status": "accepted"}),
                                 Change("delete", id=ids[2])], who="t")  # fmt: skip
    assert store.list_markings("ka", limit=2)[1] == 5 and store.list_markings("ka", statuses=["accepted"])[1] == 1
    other.delete_map("ka")
    other.create_map("ka", crs="EPSG:25832")  # made anew: its revision goes on past the old one's
    assert _count(store, "ka") == 0 and store.list_markings("ka")[1] == 0
    other.close()


def test_jobs(store):
    store.create_map("ka", crs="EPSG:25832")
    j = store.create_job("build", "ka", {"image": "a.tif"})
    info = store.get_job(j)
    assert (info.status, info.progress, info.params) == ("accepted", 0.0, {"image": "a.tif"})
    store.update_job(j, status="running", progress=42.5)
    info = store.update_job(j, status="failed", error="disk full")
    assert info.status == "failed" and info.error == "disk full" and info.finished_at is not None
    assert info.started_at is not None and info.progress == 42.5
    assert [x.id for x in store.find_jobs(kind="build", map_id="ka", status="failed")] == [j]
    with pytest.raises(StoreError, match="job status must be one of"):
        store.update_job(j, status="done")
    with pytest.raises(UnknownJobError):
        store.get_job(999)
    with pytest.raises(UnknownMapError):
        store.create_job("build", "nope")


def test_imagery_records(store):
    store.create_map("ka", crs="EPSG:25832")
    i = store.add_imagery("ka", "imagery/1.tif", "EPSG:25832", (1, 2, 3, 4), 0.1)
    info = store.get_imagery(i)
    assert (info.path, info.bounds, info.resolution_m) == ("imagery/1.tif", (1, 2, 3, 4), 0.1)
    assert [x.id for x in store.list_imagery("ka")] == [i]


def _writer(url: str, worker: int, n: int) -> None:
    store = Store(url)
    for k in range(n):
        store.add_markings("ka", [_m(worker * 100 + k, 0)], who=f"w{worker}")
    store.close()


def test_concurrent_writers_from_processes(db_url):
    Store(db_url).create_map("ka", crs="EPSG:25832")
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_writer, args=(db_url, w, 25)) for w in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0, 0, 0]
    store = Store(db_url)
    assert _count(store, "ka") == 100
    assert store.map_revision("ka") == 100


def test_add_markings_answers_each_marking_its_own_id(db_url):
    """Over several batches, after other maps' markings and a deleted map's: ids in the order given."""
    store = Store(db_url)
    for m in ("a", "b", "c"):
        store.create_map(m, crs="EPSG:25832")
    store.add_markings("a", [_m(i, 0) for i in range(30)])
    store.add_markings("b", [_m(i, 1) for i in range(20)])
    store.delete_map("b")  # the largest ids go: new ones must not reuse them
    items = [_m(i * 0.01, 2) for i in range(12_001)]  # three batches
    for i, m in enumerate(items):
        m.weight = 1.0 + i
    seen = []
    ids = store.add_markings("c", items, progress=lambda done, total: seen.append((done, total)))
    assert seen == [(5000, 12_001), (10_000, 12_001), (12_001, 12_001)]
    assert len(ids) == len(set(ids)) == len(items) and ids == sorted(ids) and ids[0] > 50
    for k in (0, 4999, 5000, 9999, 10_000, 12_000):
        got = store.get_marking("c", ids[k])
        assert got.weight == items[k].weight and math.isclose(got.x, items[k].x), k
    store.close()


def test_a_connection_lost_while_a_maps_arrays_are_read_is_an_outage(postgres_url, postgres_admin, monkeypatch):
    """Read from the driver's own server-side cursor (``_driver_parts``), a server gone between two
    parts is the store's outage (503 in the API), not a driver's exception, and the next read
    works."""
    import mapbuilder.store as store_module
    from mapbuilder.store import StoreUnavailableError

    store = Store(postgres_url)
    try:
        store.create_map("ka", crs="EPSG:25832")
        store.add_markings("ka", [_m(3.0 * k, 0.0) for k in range(30)])
        monkeypatch.setattr(store_module, "_ARRAYS_PART", 10)
        real = np.array
        calls = []

        def array_then_cut(*args, **kwargs):  # the first part converted: the server ends the session
            if kwargs.get("dtype") is float and not calls:
                calls.append(1)
                with postgres_admin.connect() as admin:
                    admin.execute(text("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = :db"),
                                  {"db": postgres_url.rsplit("/", 1)[1]})
            return real(*args, **kwargs)

        monkeypatch.setattr(store_module.np, "array", array_then_cut)
        with pytest.raises(StoreUnavailableError, match="database unavailable"):
            store.marking_arrays("ka")
        monkeypatch.setattr(store_module.np, "array", real)
        assert len(store.marking_arrays("ka")) == 30  # the pool gives a working connection again
    finally:
        store.close()


def _nested(depth: int) -> dict:
    out: dict = {}
    for _ in range(depth):
        out = {"a": out}
    return out


@pytest.mark.parametrize("extra, why", [
    ({"gain": math.inf}, "not finite"),
    ({"trace": [1.0, {"gain": -math.inf}]}, "not finite"),
    ({"gain": math.nan}, "not finite"),
    ({"seen": {1, 2}}, "extra is not JSON"),
    ({"deep": _nested(300)}, "extra is not JSON"),
])  # fmt: skip
def test_an_extra_json_cannot_hold_is_refused_and_writes_nothing(store, extra, why):
    """JSON has no NaN or Infinity: an extra holding one could be stored on SQLite, and the map
    then neither exported nor served. A create and an update are refused alike."""
    store.create_map("ka", crs="EPSG:25832")
    (mid,) = store.add_markings("ka", [_m(0, 0, extra={"gain": 2.5})])
    rev = store.map_head("ka")[0]
    with pytest.raises(InvalidMarkingError, match=f"marking 1: {why}" if "JSON" in why else why):
        store.add_markings("ka", [_m(1, 1), _m(2, 2, extra=extra)])
    with pytest.raises(InvalidMarkingError, match=why):
        store.apply_changeset("ka", [Change("update", id=mid, fields={"extra": extra})], who="t")
    with pytest.raises(InvalidMarkingError, match=why):
        store.apply_changeset("ka", [Change("create", marking=_m(3, 3, extra=extra))], who="t")
    assert _count(store, "ka") == 1 and store.map_head("ka")[0] == rev
    kept = store.get_marking("ka", mid)
    assert kept.extra == {"gain": 2.5} and kept.version == 1
    store.close()


def test_extras_are_stored_as_json_holds_them(store):
    """What Python's json took, the store takes and gives back as JSON holds it: numpy's
    numbers as numbers, tuples as lists, keys as strings, and nesting as deep as a file
    could sensibly hold."""
    store.create_map("ka", crs="EPSG:25832")
    extra = {"gain": np.float64(1.25), "n": np.int64(7), "ok": np.bool_(True), "span": (1, 2.5),
             3: "three", "deep": _nested(200), "text": "ünïcödé ✓", "none": None}  # fmt: skip
    (mid,) = store.add_markings("ka", [_m(0, 0, extra=extra)])
    want = {"gain": 1.25, "n": 7, "ok": True, "span": [1, 2.5], "3": "three", "deep": _nested(200),
            "text": "ünïcödé ✓", "none": None}  # fmt: skip
    assert store.get_marking("ka", mid).extra == want
    assert [m.extra for m in store.iter_markings("ka")] == [want]
    store.apply_changeset("ka", [Change("update", id=mid, fields={"status": "accepted"})], who="t")
    (edit,), _ = store.history("ka", limit=1)
    assert edit.before["extra"] == want and edit.after["extra"] == want and edit.after["status"] == "accepted"
    store.close()


def test_an_upgrade_names_the_numbers_json_cannot_hold(tmp_path):
    """Schema revision 0009: a map that an import gave ``Infinity`` or ``NaN`` in an extra (the
    store on SQLite took them before they were refused) reads, serves and exports again, the
    numbers kept as their names, in the edit log too; other extras are left as they were."""
    from mapbuilder.geojson import write_geojson

    url = f"sqlite:///{tmp_path / 'old.sqlite'}"
    old = Store(url, upgrade=False)
    old.upgrade("0008")
    old.create_map("ka", crs="EPSG:25832")
    ids = old.add_markings("ka", [_m(k, k) for k in range(4)])
    old.apply_changeset("ka", [Change("update", id=ids[0], fields={"status": "accepted"})], who="t")
    # What Python's json wrote for them, as the store did before.
    extras = [{"gain": math.inf, "note": "NaN is fine as text"},
              {"trace": [math.nan, -math.inf, 1.5], "deep": {"x": math.inf}},
              {"note": "Infinity and NaN, said in words"}, {}]  # fmt: skip
    with old.engine.begin() as conn:
        for i, extra in zip(ids, extras):
            conn.execute(text("UPDATE markings SET extra = :e WHERE id = :i"), dict(e=json.dumps(extra), i=i))
        state = json.loads(conn.execute(text("SELECT after FROM edits WHERE op = 'update'")).scalar_one())
        state["extra"] = extras[0]
        conn.execute(text("UPDATE edits SET before = :s, after = :s WHERE op = 'update'"), dict(s=json.dumps(state)))
        raw = conn.execute(text("SELECT extra FROM markings WHERE id = :i"), dict(i=ids[0])).scalar_one()
    old.close()
    with pytest.raises(ValueError, match="not JSON compliant"):  # what an export did before
        json.dumps(json.loads(raw), allow_nan=False)

    up = Store(url, upgrade=False)
    assert up.upgrade() == ("0008", migrate.head_revision())
    up.close()
    store = Store(url)
    got = {m.id: m.extra for m in store.iter_markings("ka")}
    assert got == {ids[0]: {"gain": "Infinity", "note": "NaN is fine as text"},
                   ids[1]: {"trace": ["NaN", "-Infinity", 1.5], "deep": {"x": "Infinity"}},
                   ids[2]: {"note": "Infinity and NaN, said in words"}, ids[3]: {}}  # fmt: skip
    (edit,), _ = store.history("ka", limit=1)
    assert edit.before["extra"]["gain"] == "Infinity" and edit.after["extra"]["gain"] == "Infinity"
    assert store.get_marking("ka", ids[0]).status == "accepted" and store.map_head("ka")[0] == 2
    out = tmp_path / "ka.geojson"
    write_geojson(out, store.iter_markings("ka"))
    assert json.loads(out.read_text())["features"][0]["properties"]["gain"] == "Infinity"
    store.close()


def test_a_box_is_counted_once_a_revision_and_every_write_counts_it_again(store, db_url):
    """Paging through a box asks for its count with every page. The count is read once for
    each state of the map, however many pages ask, and each way of writing markings, by this
    store or by another process's, has the next page count again."""
    from sqlalchemy import event

    store.create_map("ka", crs="EPSG:25832")
    ids = store.add_markings("ka", [_m(5 * k, 0, source="detected", score=k / 40) for k in range(40)]
                             + [_m(0, 500), _m(500, 500)])  # fmt: skip
    box = tuple(store.get_map("ka").bounds_wgs84())
    box = (box[0] - 1e-4, box[1] - 1e-4, box[0] + (box[2] - box[0]) * 0.4, box[1] + (box[3] - box[1]) * 0.2)
    counts: list[str] = []

    @event.listens_for(store.engine, "before_cursor_execute")
    def _seen(conn, cursor, statement, *args):
        if "count(" in statement.lower():
            counts.append(statement)

    def pages(statuses=None) -> tuple[int, list[int]]:
        got, totals = [], set()
        for offset in range(0, 60, 7):
            page, total = store.query_lonlat_box("ka", box, statuses=statuses, limit=7, offset=offset)
            got += [m.id for m in page]
            totals.add(total)
        assert len(totals) == 1
        return totals.pop(), got

    assert pages() == (40, ids[:40]) and len(counts) == 1
    assert pages(["unreviewed"]) == (40, ids[:40]) and len(counts) == 2  # another selection, its own count
    assert store.count_markings("ka", lonlat_box=box) == 40 and len(counts) == 2
    queue = [m.id for m in store.review_queue("ka", lonlat_box=box, limit=100)[0]]
    assert queue == ids[:40] and store.review_queue("ka", lonlat_box=box, limit=5)[1] == 40 and len(counts) == 3

    writes = [
        (lambda: store.add_markings("ka", [_m(1, 1)]), 41),
        (lambda: store.apply_changeset("ka", [Change("delete", id=ids[3])], who="t"), 40),
        (lambda: store.apply_changeset("ka", [Change("update", id=ids[0], fields={"x": E0 + 500})], who="t"), 39),
        (lambda: store.bulk_load("ka", [_m(2, 2), _m(3, 3)]), 41),
    ]  # fmt: skip
    for write, want in writes:
        write()
        assert pages()[0] == want and store.count_markings("ka", lonlat_box=box) == want
    review = store.review_by_score("ka", reject_below=0.5, lonlat_box=box, who="t")
    assert review.rejected > 0
    assert pages(["unreviewed"])[0] == 41 - review.rejected
    assert store.review_queue("ka", lonlat_box=box, limit=5)[1] == 38 - review.rejected
    store.revert_changeset("ka", review.changeset_id, who="t")
    assert pages(["unreviewed"])[0] == 41 and store.review_queue("ka", lonlat_box=box)[1] == 38

    other = Store(db_url)  # another server process
    other.add_markings("ka", [_m(4, 4)])
    other.close()
    assert pages() == (42, pages()[1]) and store.count_markings("ka", lonlat_box=box) == 42
    store.delete_map("ka")
    store.create_map("ka", crs="EPSG:25832")
    store.add_markings("ka", [_m(5 * k, 0) for k in range(40)])
    assert pages()[0] == 40
    store.close()
