"""The change feed (``Store.changes``): a copy of a map kept up to date from the changes since
its revision, on a real SQLite file and a real PostgreSQL server."""

from __future__ import annotations

import threading

import pytest
from sqlalchemy import text

from mapbuilder import migrate
from mapbuilder.model import Marking
from mapbuilder.store import Change, ConflictError, StaleRevisionError, Store, StoreError

E0, N0 = 457000.0, 5428000.0  # Karlsruhe, EPSG:25832


def _m(dx: float, dy: float = 0.0, **kw) -> Marking:
    return Marking(x=E0 + dx, y=N0 + dy, length_m=3.0, width_m=0.12, weight=36, **kw)


class Copy:
    """What a fleet keeps: markings by id, and the revision they are at."""

    def __init__(self, statuses=None):
        self.markings: dict[int, tuple] = {}
        self.revision = 0
        self.statuses = statuses
        self.pages = 0

    def sync(self, store: Store, map_id: str, limit: int = 1000) -> None:
        after = None
        while True:
            page = store.changes(map_id, self.revision, statuses=self.statuses, after=after, limit=limit)
            assert len(page.changed) + len(page.removed) <= limit
            for _, i in page.removed:
                self.markings.pop(i, None)
            for _, m in page.changed:
                self.markings[m.id] = _state(m)
            self.pages += 1
            if not page.more:
                self.revision = page.revision
                return
            after = page.after


def _state(m: Marking) -> tuple:
    return (m.version, m.status, round(m.x, 6), round(m.y, 6), m.kind, m.source)


def _truth(store: Store, map_id: str, statuses=None) -> dict[int, tuple]:
    return {m.id: _state(m) for m in store.iter_markings(map_id, statuses=statuses)}


def test_a_copy_follows_every_kind_of_write(store):
    """Imports, edits, deletes, reverts (a deleted marking back under its id) and rebuilt tiles:
    after each, a copy that applies the changes since its revision, a few at a time, equals the
    map; one that keeps only what the localizer uses drops what was rejected."""
    store.create_map("ka", crs="EPSG:25832")
    full, fleet, paged = Copy(), Copy(statuses=("accepted", "unreviewed")), Copy()

    def check():
        full.sync(store, "ka")
        fleet.sync(store, "ka")
        paged.sync(store, "ka", limit=3)
        assert full.markings == paged.markings == _truth(store, "ka")
        assert fleet.markings == _truth(store, "ka", statuses=("accepted", "unreviewed"))
        assert full.revision == fleet.revision == store.get_map("ka").revision

    check()  # nothing yet
    ids = store.add_markings("ka", [_m(3.0 * k) for k in range(10)])
    check()
    res = store.apply_changeset("ka", [
        Change("update", id=ids[0], fields={"status": "accepted"}),
        Change("update", id=ids[1], fields={"status": "rejected"}),
        Change("delete", id=ids[2]),
        Change("create", marking=_m(100.0, kind="stop_line")),
    ], who="t")  # fmt: skip
    check()
    assert ids[1] not in fleet.markings and ids[1] in full.markings
    store.revert_changeset("ka", res.changeset_id, who="t")  # marking ids[2] comes back under its id
    check()
    assert ids[2] in full.markings and ids[1] in fleet.markings
    # a rebuilt tile: its unreviewed detections give way to new ones, a reviewed one stays
    first = store.replace_detected("ka", "t1", [_m(200.0 + k) for k in range(5)])
    check()
    det = [i for i, s in full.markings.items() if s[5] == "detected"]
    store.apply_changeset("ka", [Change("update", id=det[0], fields={"status": "accepted"})], who="t")
    assert store.replace_detected("ka", "t1", [_m(200.3 + k) for k in range(5)]) == first - 1
    check()
    assert det[0] in full.markings and not set(det[1:]) & set(full.markings)
    # a write that fails changes nothing a copy sees
    rev = store.get_map("ka").revision
    with pytest.raises(ConflictError):
        store.apply_changeset("ka", [Change("delete", id=ids[3], version=7)], who="t")
    assert store.get_map("ka").revision == rev
    assert store.changes("ka", rev).changed == [] and store.changes("ka", rev).removed == []
    check()
    assert paged.pages > full.pages  # it did go page by page


def test_changes_name_their_revisions_and_refuse_a_revision_the_map_never_reached(store):
    store.create_map("ka", crs="EPSG:25832")
    a = store.add_markings("ka", [_m(0.0), _m(3.0)])
    r1 = store.get_map("ka").revision
    store.apply_changeset("ka", [Change("delete", id=a[0])], who="t")
    r2 = store.get_map("ka").revision
    page = store.changes("ka", 0)
    assert [(r, m.id) for r, m in page.changed] == [(r1, a[1])] and page.removed == [(r2, a[0])]
    assert (page.revision, page.more, page.after) == (r2, False, (r2, a[0]))
    assert store.changes("ka", r1).changed == [] and store.changes("ka", r1).removed == [(r2, a[0])]
    with pytest.raises(StoreError, match=">= 0"):
        store.changes("ka", -1)
    # the map made anew: a copy of the old one is told to read it whole, even once the new map
    # has been written as often as the old one was (its revisions go on past the old one's)
    store.delete_map("ka")
    store.create_map("ka", crs="EPSG:25832")
    assert store.get_map("ka").revision == store.get_map("ka").feed_since == r2 + 1
    with pytest.raises(StaleRevisionError, match="made anew"):
        store.changes("ka", r2)
    b = store.add_markings("ka", [_m(6.0)])
    store.add_markings("ka", [_m(9.0)])
    assert store.get_map("ka").revision == r2 + 3
    for since in (r1, r2):
        with pytest.raises(StaleRevisionError, match=f"from revision {r2 + 1} on"):
            store.changes("ka", since)
    fresh = Copy()
    fresh.sync(store, "ka")
    assert fresh.markings == _truth(store, "ka") and b[0] in fresh.markings
    # a copy from a database restored from an older backup: beyond the map's revision
    with pytest.raises(StaleRevisionError, match="older backup"):
        store.changes("ka", r2 + 10)
    # made anew twice: past the second one's last revision
    store.delete_map("ka")
    store.create_map("ka")
    assert store.get_map("ka").revision == r2 + 4


def test_a_copy_synchronised_between_two_writers_misses_neither(db_url, monkeypatch):
    """Writer A has stamped its marking and not committed; writer B writes the same map; a copy
    is synchronised meanwhile, and again once both are done. It must hold both markings: a
    revision is taken in commit order, so B cannot publish a revision past A's uncommitted one
    (with revisions read at the start and bumped at the end, the copy skipped A's marking)."""
    store = Store(db_url)
    store.create_map("ka", crs="EPSG:25832")
    store.add_markings("ka", [_m(0.0)])
    copy = Copy()
    copy.sync(store, "ka")
    a_waiting, release_a = threading.Event(), threading.Event()
    touch = Store._touch_map

    def slow_for_a(self, conn, map_id, xs=(), ys=()):
        if threading.current_thread().name == "A":
            a_waiting.set()
            assert release_a.wait(60)
        return touch(self, conn, map_id, xs, ys)

    monkeypatch.setattr(Store, "_touch_map", slow_for_a)
    errors: list[BaseException] = []

    def write(x: float) -> None:
        s = Store(db_url)
        try:
            s.apply_changeset("ka", [Change("create", marking=_m(x))], who=threading.current_thread().name)
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)
        finally:
            s.close()

    a = threading.Thread(target=write, args=(10.0,), name="A")
    b = threading.Thread(target=write, args=(20.0,), name="B")
    a.start()
    assert a_waiting.wait(60)
    b.start()
    b.join(1.0)  # B writes as far as it may while A holds on
    copy.sync(store, "ka")
    release_a.set()
    a.join(60)
    b.join(60)
    assert not errors, errors
    copy.sync(store, "ka")
    assert len(copy.markings) == 3 and copy.markings == _truth(store, "ka")
    store.close()


def test_markings_stored_before_the_feed_are_in_it_after_the_upgrade(db_url):
    """``lanemap db upgrade`` from the first schema: every marking already stored is stamped
    with its map's revision, so a copy taken from nothing gets it, and one at that revision
    gets nothing."""
    old = Store(db_url, upgrade=False)
    old.upgrade("0001")
    with old.engine.begin() as conn:
        conn.execute(text("INSERT INTO maps (id, title, crs, revision, created_at, updated_at) "
                          "VALUES ('old', '', 'EPSG:25832', 7, CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"))
        for k in range(3):
            conn.execute(text(
                "INSERT INTO markings (map_id, gx, gy, x, y, lon, lat, weight, length_m, width_m, bearing_deg, "
                "source, status, extra, version, created_at, updated_at) VALUES ('old', 0, 0, :x, :y, 8.4, 49.0, "
                "1, 3, 0.15, 0, 'imported', 'unreviewed', '{}', 1, CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"
            ), {"x": E0 + k, "y": N0})  # fmt: skip
    old.close()
    with pytest.raises(StoreError, match="lanemap db upgrade"):
        Store(db_url)
    up = Store(db_url, upgrade=False)
    assert up.upgrade() == ("0001", migrate.head_revision())
    up.close()
    store = Store(db_url)
    page = store.changes("old", 0)
    assert [r for r, _ in page.changed] == [7, 7, 7] and page.removed == [] and page.revision == 7
    assert store.changes("old", 7).changed == []
    # and it goes on from there
    store.apply_changeset("old", [Change("delete", id=page.changed[0][1].id)], who="t")
    assert store.changes("old", 7).removed == [(8, page.changed[0][1].id)]
    store.close()


def test_old_deletions_are_pruned_and_older_copies_read_the_map_whole(store, tmp_path, monkeypatch):
    """``prune_removed`` / ``lanemap maps prune-feed``: deletions before a time go, the feed answers
    copies from the newest pruned revision on, an older copy is told to read the map whole (and
    reading from nothing still works), a newer one syncs as before."""
    from datetime import UTC, datetime, timedelta

    store.create_map("ka", crs="EPSG:25832")
    ids = store.add_markings("ka", [_m(3.0 * k) for k in range(6)])
    old_copy = Copy()
    old_copy.sync(store, "ka")
    store.apply_changeset("ka", [Change("delete", id=ids[0])], who="t")
    middle = Copy()
    middle.sync(store, "ka")
    horizon = store.get_map("ka").revision
    cutoff = datetime.now(UTC) + timedelta(seconds=1)  # everything so far is older
    assert store.get_map("ka").feed_since == 0
    assert store.prune_removed("ka", cutoff) == (1, horizon)
    assert store.get_map("ka").feed_since == horizon
    store.apply_changeset("ka", [Change("delete", id=ids[1])], who="t")
    with pytest.raises(StaleRevisionError, match=f"from revision {horizon} on"):
        store.changes("ka", old_copy.revision)
    middle.sync(store, "ka")  # at the horizon: goes on
    assert middle.markings == _truth(store, "ka")
    fresh = Copy()
    fresh.sync(store, "ka")
    assert fresh.markings == _truth(store, "ka")
    # nothing older than a cutoff in the past: nothing goes, the horizon stays
    assert store.prune_removed("ka", datetime.now(UTC) - timedelta(days=1)) == (0, horizon)
    if store.dialect == "sqlite":  # the command, once
        from typer.testing import CliRunner

        from service.cli import app

        monkeypatch.setenv("LANEMAP_DATABASE_URL", store.url)
        res = CliRunner().invoke(app, ["maps", "prune-feed", "ka", "--older-than", "0"])
        assert res.exit_code == 0, res.output
        assert res.stdout.strip() == (f"map ka: 1 deletions forgotten; the change feed answers copies at revision "
                                      f"{horizon + 1} or later (older ones read the map whole)")
        res = CliRunner().invoke(app, ["maps", "prune-feed", "ka", "--older-than", "-1"])
        assert res.exit_code == 2
        for args in (["ka", "--all"], []):  # a map or every map, not both, not neither
            res = CliRunner().invoke(app, ["maps", "prune-feed", *args, "--older-than", "1"])
            assert res.exit_code == 2 and "name a MAP or give --all" in res.output


def test_every_maps_feed_is_pruned_at_once(store, monkeypatch):
    """``prune_all_removed`` / ``prune-feed --all``: each map with old deletions is pruned, a map
    without any is left as it is."""
    from datetime import UTC, datetime, timedelta

    horizons = {}
    for map_id in ("a", "b", "c"):
        store.create_map(map_id, crs="EPSG:25832")
        ids = store.add_markings(map_id, [_m(3.0 * k) for k in range(4)])
        if map_id != "c":
            store.apply_changeset(map_id, [Change("delete", id=i) for i in ids[: 2 if map_id == "a" else 1]], who="t")
        horizons[map_id] = store.get_map(map_id).revision
    cutoff = datetime.now(UTC) + timedelta(seconds=1)
    assert store.prune_all_removed(cutoff) == {"a": (2, horizons["a"]), "b": (1, horizons["b"])}
    assert [store.get_map(m).feed_since for m in "abc"] == [horizons["a"], horizons["b"], 0]
    assert store.prune_all_removed(cutoff) == {}
    store.apply_changeset("c", [Change("delete", id=store.add_markings("c", [_m(50.0)])[0])], who="t")
    if store.dialect == "sqlite":
        from typer.testing import CliRunner

        from service.cli import app

        monkeypatch.setenv("LANEMAP_DATABASE_URL", store.url)
        res = CliRunner().invoke(app, ["maps", "prune-feed", "--all", "--older-than", "1"])
        assert res.exit_code == 0 and res.stdout.strip() == "no map recorded deletions more than 1 day ago"
        res = CliRunner().invoke(app, ["maps", "prune-feed", "--all", "--older-than", "0"])
        assert res.exit_code == 0, res.output
        assert res.stdout.strip() == (f"map c: 1 deletions forgotten; the change feed answers copies at revision "
                                      f"{store.get_map('c').revision} or later (older ones read the map whole)")
    store.close()
