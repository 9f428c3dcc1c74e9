"""The service's cache of map indexes (``service.index_cache.IndexCache``) on a real SQLite store.

What a fleet relies on while a map is edited: a large map answers from its
previous index while the next is built, a build never holds other maps'
requests, and an index is never taken for a map it was not built from.
"""

from __future__ import annotations

import logging
import re
import threading
import time

import numpy as np
import pytest

from mapbuilder.model import Marking
from mapbuilder.store import Store, UnknownMapError
from service.index_cache import IndexCache, IndexPending
from service.problems import Problem

CRS = "EPSG:25832"


class GatedStore(Store):
    """A real store whose reads of a map's markings (the index builds', and the changes its
    updates read) wait for ``gate``, and then fail with ``fail`` when it is set."""

    def __init__(self, url: str):
        super().__init__(url)
        self.gate = threading.Event()
        self.gate.set()
        self.reading = threading.Event()
        self.fail: Exception | None = None

    def _wait_at_gate(self) -> None:
        self.reading.set()
        assert self.gate.wait(30), "the test never opened the gate"
        if self.fail is not None:
            raise self.fail

    def marking_arrays(self, map_id, *args, **kwargs):
        self._wait_at_gate()
        return super().marking_arrays(map_id, *args, **kwargs)

    def changes(self, map_id, *args, **kwargs):
        self._wait_at_gate()
        return super().changes(map_id, *args, **kwargs)


def _markings(n: int, x0: float = 457_000.0, seed: int = 0) -> list[Marking]:
    rng = np.random.default_rng(seed)
    return [Marking(x=x0 + 3.0 * k, y=5_428_000.0 + rng.normal(0, 0.05), length_m=3.0, width_m=0.12,
                    bearing_deg=90.0, weight=40.0, kind="dash") for k in range(n)]  # fmt: skip


@pytest.fixture
def store(tmp_path):
    s = GatedStore(f"sqlite:///{tmp_path / 'maps.sqlite'}")
    for map_id in ("a", "b"):
        s.create_map(map_id, crs=CRS)
        s.add_markings(map_id, _markings(30))
    yield s
    s.gate.set()
    s.close()


def _ready(cache: IndexCache, map_id: str):
    """The map's index once built, as a request that waited for it gets it."""
    with pytest.raises(IndexPending) as pending:
        cache.lookup(map_id)
    pending.value.future.result(timeout=30)
    return cache.lookup(map_id, accept_stale=True)


def _rested(cache: IndexCache, map_id: str) -> None:
    """Until the map may be built in the background again (``build_share``)."""
    time.sleep(max(0.0, cache._rest_until.get(map_id, 0.0) - time.monotonic()) + 0.01)


def _build_under_way(cache: IndexCache, map_id: str):
    return cache._building[map_id][1]


def test_a_large_map_answers_from_its_previous_index_while_the_next_is_built(store):
    cache = IndexCache(store, "hull", background_from=0, build_share=0.5)
    try:
        a, stale = _ready(cache, "a")
        assert not stale and len(a.index) == 30 and a.revision == store.map_head("a").revision
        b, _ = _ready(cache, "b")
        _rested(cache, "a")
        store.add_markings("a", _markings(5, x0=457_090.0))
        store.gate.clear()
        store.reading.clear()
        old, stale = cache.lookup("a")  # at once, though the build waits at the gate
        assert stale and old is a and old.revision < store.map_head("a").revision
        assert store.reading.wait(10)  # the build is under way...
        assert cache.lookup("b") == (b, False)  # ...and holds no other map's requests
        build = _build_under_way(cache, "a")
        assert cache.lookup("a") == (a, True) and _build_under_way(cache, "a") is build  # no second build
        time.sleep(0.5)  # a build of half a second at least
        store.gate.set()
        build.result(timeout=30)
        new, stale = cache.lookup("a")
        assert not stale and len(new.index) == 35 and new.revision == store.map_head("a").revision
        # the next edit's build waits as long as the last build took: builds take at most half the time
        store.add_markings("a", _markings(5, x0=457_200.0))
        assert cache.lookup("a") == (new, True) and "a" not in cache._building
        assert cache._rest_until["a"] - time.monotonic() > 0.3  # the last build took 0.5 s or more
        _rested(cache, "a")
        assert cache.lookup("a") == (new, True) and "a" in cache._building
        _build_under_way(cache, "a").result(timeout=30)
        assert len(cache.lookup("a")[0].index) == 40
    finally:
        cache.close()


def test_a_small_map_waits_for_its_new_index(store):
    cache = IndexCache(store, "hull", background_from=31, build_share=1.0)
    try:
        _ready(cache, "a")
        store.add_markings("a", _markings(5, x0=457_090.0))
        new, stale = _ready(cache, "a")
        assert not stale and len(new.index) == 35
        # grown past the bound, the map now answers from its previous index while it changes
        store.add_markings("a", _markings(5, x0=457_200.0))
        assert cache.lookup("a")[1] is True
    finally:
        cache.close()


def test_an_index_is_never_taken_for_another_map_or_coverage(store):
    cache = IndexCache(store, "hull", background_from=0, build_share=1.0)
    try:
        first, _ = _ready(cache, "a")
        # a map made anew under the id: its revisions go on, but nothing of the old index may answer
        store.delete_map("a")
        with pytest.raises(UnknownMapError):
            cache.lookup("a")
        store.create_map("a", crs=CRS)
        store.add_markings("a", _markings(12, x0=458_000.0))
        with pytest.raises(IndexPending):
            cache.lookup("a", accept_stale=True)
        made_anew, _ = _ready(cache, "a")
        assert len(made_anew.index) == 12 and made_anew.created != first.created
        # a coverage set on the map is answered only by an index drawn by it
        store.update_map("a", coverage="markings", set_coverage=True)
        with pytest.raises(IndexPending):
            cache.lookup("a")
        by_markings, _ = _ready(cache, "a")
        assert by_markings.coverage == "markings" and by_markings.index.extent.rule == "markings"
    finally:
        cache.close()


def test_a_map_without_markings_is_a_problem_and_a_failed_build_is_tried_again(store):
    cache = IndexCache(store, "hull", background_from=0, build_share=1.0)
    try:
        store.create_map("empty")
        with pytest.raises(IndexPending) as pending:
            cache.lookup("empty")
        with pytest.raises(Problem) as problem:
            pending.value.future.result(timeout=30)
        assert problem.value.status == 409
        with pytest.raises(UnknownMapError):
            cache.lookup("nope")

        before, _ = _ready(cache, "a")
        store.add_markings("a", _markings(5, x0=457_090.0))
        store.gate.clear()  # each build is held until the test holds its future
        store.fail = OSError("disk gone")
        assert cache.lookup("a") == (before, True)
        failing = _build_under_way(cache, "a")
        store.gate.set()
        with pytest.raises(OSError):
            failing.result(timeout=30)
        store.fail = None
        store.gate.clear()
        assert cache.lookup("a") == (before, True)  # still answering, and building again
        again = _build_under_way(cache, "a")
        store.gate.set()
        again.result(timeout=30)
        assert len(cache.lookup("a")[0].index) == 35
    finally:
        cache.close()


def test_closing_cancels_the_builds_not_begun_and_never_holds_the_process():
    """A server asked to stop does not first build indexes nobody will use."""
    from service.index_cache import _Builder

    builder, started, release = _Builder(), threading.Event(), threading.Event()
    before = set(threading.enumerate())
    running = builder.submit(lambda: (started.set(), release.wait(30), "built")[-1])
    queued = builder.submit(lambda: "never")
    assert started.wait(10)
    (worker,) = [t for t in threading.enumerate() if t not in before and t.name == "lanemap-index"]
    assert worker.daemon  # the interpreter's exit does not wait for it
    builder.close()
    release.set()
    assert running.result(timeout=10) == "built"
    worker.join(10)
    assert not worker.is_alive() and queued.cancelled()
    assert builder.submit(lambda: "again").result(timeout=10) == "again"  # a new start builds again
    builder.close()


def test_a_request_that_stops_waiting_leaves_the_build_to_the_others():
    """A client gone while its request waits for a queued build does not cancel that build."""
    import asyncio
    import concurrent.futures

    build: concurrent.futures.Future = concurrent.futures.Future()  # queued: not running yet
    pending = IndexPending("a", build)

    async def give_up():
        with pytest.raises(asyncio.TimeoutError):
            await asyncio.wait_for(pending.wait(), 0.05)

    asyncio.run(give_up())
    assert not build.cancelled() and build.set_running_or_notify_cancel()


def test_the_memory_a_build_frees_goes_back_to_the_system_where_glibc_runs():
    """glibc keeps a build's freed pages (ten times the index's size) unless asked: the builder
    finds its ``malloc_trim`` wherever the C library is glibc, as on the Debian this runs on."""
    import platform

    from service import index_cache

    assert (index_cache._malloc_trim is not None) == (platform.libc_ver()[0] == "glibc")
    index_cache._trim_heap()


def _files(tmp_path, store):
    from service.index_files import IndexFiles, database_identity

    return IndexFiles(tmp_path / "indexes", database_identity(store.engine.url), min_markings=1)


def _kept_by_a_first_process(store, tmp_path, coverage: str):
    """Map "a"'s index as a first server process builds and keeps it, and stops."""
    first = IndexCache(store, coverage, background_from=0, files=_files(tmp_path, store))
    try:
        return _ready(first, "a")[0]
    finally:
        first.close()


def test_a_process_that_starts_reads_the_index_another_kept(store, tmp_path):
    """The next worker (or the server started again) reads the map's index from the file the first
    kept, without reading the map's markings, and answers at the map's revision."""
    built = _kept_by_a_first_process(store, tmp_path, "markings")
    store.gate.clear()  # a build would wait here
    store.reading.clear()
    second = IndexCache(store, "markings", background_from=0, files=_files(tmp_path, store))
    try:
        read, stale = _ready(second, "a")
        assert not stale and not store.reading.is_set()
        assert read.revision == built.revision and len(read.index) == len(built.index) == 30
        assert read.index.extent.area.equals(built.index.extent.area)
        assert "a" not in second._building  # current: nothing more to build
    finally:
        store.gate.set()
        second.close()


def test_an_index_kept_current_by_updates_is_kept_again_after_enough_edits_or_time(store, tmp_path, monkeypatch,
                                                                                   caplog):  # fmt: skip
    """A server that edits a map all day keeps its index in a file again once a twentieth of the
    map was written since the last (then a start updates the file's index rather than build
    one), or an hour after the last if anything was; not after each edit."""
    from mapbuilder.store import Change
    from service import index_cache

    from prometheus_client import REGISTRY

    def saves(after: str) -> float:
        return REGISTRY.get_sample_value("lanemap_index_file_saves_total", {"after": after}) or 0.0

    files = _files(tmp_path, store)
    cache = IndexCache(store, "hull", background_from=1000, files=files)
    built, updated = saves("build"), saves("update")
    try:
        first, _ = _ready(cache, "a")
        assert files.load("a", store.map_head("a"), "hull").revision == first.revision
        assert saves("build") == built + 1
        ids = [m.id for m in store.query_bbox("a", 456_000, 5_427_000, 458_000, 5_429_000)][:2]

        def edit(i: int) -> int:
            weight = 50.0 + store.map_head("a").revision  # another each time
            store.apply_changeset("a", [Change("update", id=ids[i], fields={"weight": weight})], who="test")
            with caplog.at_level(logging.INFO, logger="service.index_cache"):
                now, stale = _ready(cache, "a")
            assert not stale and "updated from revision" in caplog.text
            return now.revision

        edit(0)  # 1 of 30 markings: not yet a twentieth
        assert files.load("a", store.map_head("a"), "hull").revision == first.revision
        revision = edit(1)
        assert files.load("a", store.map_head("a"), "hull").revision == revision
        assert f"spatial index at revision {revision} kept in" in caplog.text and saves("update") == updated + 1
        assert len(list(files.directory.glob("*.index"))) == 1
        monkeypatch.setattr(index_cache, "KEEP_AFTER_S", 0.0)  # as if an hour passed
        revision = edit(0)
        assert files.load("a", store.map_head("a"), "hull").revision == revision
        second = IndexCache(store, "hull", background_from=1000, files=files)  # a start reads it, current
        try:
            store.reading.clear()
            read, stale = _ready(second, "a")
            assert read.revision == revision and not store.reading.is_set()
        finally:
            second.close()
    finally:
        cache.close()


def test_a_large_map_edited_meanwhile_answers_from_the_kept_index_until_the_newest_is_built(store, tmp_path):
    built = _kept_by_a_first_process(store, tmp_path, "hull")
    store.add_markings("a", _markings(5, x0=457_090.0))  # while no server ran
    store.delete_map("b")
    store.gate.clear()
    store.reading.clear()
    files = _files(tmp_path, store)
    second = IndexCache(store, "hull", background_from=30, files=files)
    try:
        assert second.preload() == ["a"]  # as a server starts
        assert store.reading.wait(10)  # the newest is being built, no request having asked...
        old, stale = second.lookup("a")  # ...and meanwhile the kept one answers
        assert stale and old.revision == built.revision and len(old.index) == 30
        store.gate.set()
        _build_under_way(second, "a").result(timeout=30)
        new, stale = second.lookup("a")
        assert not stale and len(new.index) == 35 and new.revision == store.map_head("a").revision
        kept = files.load("a", store.map_head("a"), "hull")
        assert kept.revision == new.revision and len(list(files.directory.glob("*.index"))) == 1  # the older went
    finally:
        store.gate.set()
        second.close()


def test_a_small_map_never_answers_from_an_older_kept_index(store, tmp_path):
    _kept_by_a_first_process(store, tmp_path, "hull")
    store.add_markings("a", _markings(5, x0=457_090.0))
    second = IndexCache(store, "hull", background_from=1000, files=_files(tmp_path, store))
    try:
        new, stale = _ready(second, "a")
        assert not stale and len(new.index) == 35
    finally:
        second.close()


def test_a_large_maps_index_is_built_in_a_child_process_and_handed_over_in_its_file(tmp_path, caplog):
    """``process_from``: the build runs in a process of its own (its interpreter and memory are not
    the server's), which keeps the index in a file this process reads; where the file cannot be
    written, the request is told to come back (503), and nothing is taken for the index."""
    import logging
    import os

    from service.index_files import IndexFiles, database_identity

    url = f"sqlite:///{tmp_path / 'maps.sqlite'}"
    store = Store(url)
    store.create_map("a", crs=CRS)
    store.add_markings("a", _markings(40))
    files = IndexFiles(tmp_path / "indexes", database_identity(url), min_markings=1)
    cache = IndexCache(store, "markings", background_from=0, files=files, process_from=40)
    caplog.set_level(logging.INFO, logger="service.index_cache")
    from prometheus_client import REGISTRY

    def saves() -> float:
        return REGISTRY.get_sample_value("lanemap_index_file_saves_total", {"after": "build"}) or 0.0

    before = saves()
    try:
        built, stale = _ready(cache, "a")
        assert not stale and len(built.index) == 40 and built.revision == store.map_head("a").revision
        assert saves() == before + 1  # the child's, counted here
        pid = int(re.search(r"map a: spatial index of 40 markings .* built by process (\d+)", caplog.text).group(1))
        assert pid != os.getpid()
        here = IndexCache(store, "markings", background_from=0)  # the same map built in this process
        assert _ready(here, "a")[0].index.extent.area.equals(built.index.extent.area)
        here.close()
    finally:
        cache.close()
    (tmp_path / "blocked").write_text("a file where the folder would be")
    blocked = IndexCache(store, "hull", background_from=0, process_from=40,
                         files=IndexFiles(tmp_path / "blocked", database_identity(url), min_markings=1))
    try:
        with pytest.raises(IndexPending) as pending:
            blocked.lookup("a")
        with pytest.raises(Problem) as problem:
            pending.value.future.result(timeout=60)
        assert problem.value.status == 503 and "its file could not be written" in str(problem.value)
        assert "a" not in blocked._maps
    finally:
        blocked.close()
    # a map deleted before its child read it is an unknown map (404), not a failed build (503)
    store.create_map("gone", crs=CRS)
    store.add_markings("gone", _markings(40))
    created = store.map_head("gone").created

    class DeletedFirst(Store):
        def get_map(self, map_id, **kw):
            info = super().get_map(map_id, **kw)
            if map_id == "gone" and kw.get("with_count"):
                store.delete_map(map_id)  # after the build has read the map's head, before the child starts
            return info

    deleting = DeletedFirst(url)
    late = IndexCache(deleting, "hull", background_from=0, process_from=40, files=files)
    try:
        with pytest.raises(IndexPending) as pending:
            late.lookup("gone")
        with pytest.raises(UnknownMapError):
            pending.value.future.result(timeout=60)
        assert not [p for p in files.directory.glob("*.index") if files._map_key("gone", created) in p.name]
    finally:
        late.close()
        deleting.close()
        store.close()


def test_a_map_deleted_while_its_index_is_kept_leaves_no_file(store, tmp_path):
    """The deletion removes the map's kept files, but a build that read the map just before may
    write its file just after: the build looks again, and removes it."""
    from service.index_files import IndexFiles, database_identity

    cache = None

    class DeletedMeanwhile(IndexFiles):
        def save(self, map_id, head, coverage, index, force=False):
            store.delete_map(map_id)  # as DELETE /collections/{id} would, between the build's read and its save
            cache.drop(map_id, head.created)
            return super().save(map_id, head, coverage, index, force)

    files = DeletedMeanwhile(tmp_path / "indexes", database_identity(store.engine.url), min_markings=1)
    cache = IndexCache(store, "hull", background_from=0, files=files)
    try:
        with pytest.raises(IndexPending) as pending:
            cache.lookup("a")
        pending.value.future.result(timeout=30)
        assert not list(files.directory.glob("*.index"))
        with pytest.raises(UnknownMapError):
            cache.lookup("a")
    finally:
        cache.close()


def test_an_edit_updates_the_index_and_an_update_refused_is_a_build(store, monkeypatch, caplog):
    """A small map (it waits for its new index) after an edit: updated with the edit, not built;
    where the update refuses the changes (values a build checks too), built anew, with a warning."""
    from localizer import LocalizationInputError
    from service import index_cache

    cache = IndexCache(store, "hull", background_from=1000)
    try:
        _ready(cache, "a")
        store.add_markings("a", _markings(5, x0=457_090.0))
        with caplog.at_level(logging.INFO, logger="service.index_cache"):
            new, stale = _ready(cache, "a")
        assert not stale and len(new.index) == 35 and "updated from revision" in caplog.text
        caplog.clear()

        def refuse(*args, **kwargs):
            raise LocalizationInputError("key: keys must be unique")

        monkeypatch.setattr(index_cache, "updated_index", refuse)
        store.add_markings("a", _markings(5, x0=457_200.0))
        with caplog.at_level(logging.INFO, logger="service.index_cache"):
            new, stale = _ready(cache, "a")
        assert not stale and len(new.index) == 40 and new.revision == store.map_head("a").revision
        assert "could not be updated (key: keys must be unique); building it anew" in caplog.text
        assert "spatial index of 40 markings at revision" in caplog.text  # the build's own line
    finally:
        cache.close()

@pytest.mark.parametrize("coverage", ["hull", "markings"])
def test_an_index_updated_from_the_change_feed_is_the_one_built_anew(db_url, coverage, monkeypatch,
                                                                     karlsruhe_markings, caplog):  # fmt: skip
    """A real SQLite file and PostgreSQL server: the Karlsruhe map with detections beside it, then
    edits of every kind a person or a build makes (moves, kinds, weights, deletions, creations,
    detections rejected and accepted, a changeset reverted): the index updated with the change
    feed since it was built is the one built from the map as it is, revision after revision."""
    from mapbuilder.store import Change
    from service.map_index import load_index, updated_index

    from ._localizer_helpers import CRS

    store = Store(db_url)
    try:
        store.create_map("ka", "Karlsruhe", CRS)
        store.add_markings("ka", karlsruhe_markings)
        rng = np.random.default_rng(11)
        detected = [Marking(x=457_300.0 + 9.0 * k, y=5_428_650.0 + 3.5 * (k % 2) + rng.normal(0, 0.05),
                            length_m=float(rng.choice([3.0, 1.2, 3.1])), width_m=0.12, bearing_deg=90.0,
                            weight=30.0, source="detected", score=float(rng.uniform(0.2, 0.9)))
                    for k in range(60)]  # fmt: skip
        store.add_markings("ka", detected)
        index = load_index(store, "ka", CRS, coverage)
        _ = index.extent
        revision = store.map_head("ka").revision
        ids = [m.id for m in store.iter_markings("ka")]
        edits = [
            [Change("update", id=ids[3], fields={"x": store.get_marking("ka", ids[3]).x + 4.0}),
             Change("update", id=ids[10], fields={"kind": None}), Change("update", id=ids[11], fields={"weight": 99.0}),
             Change("delete", id=ids[20])],
            [Change("create", marking=Marking(x=457_250.0, y=5_428_640.0, length_m=3.0, width_m=0.12,
                                              bearing_deg=12.0, weight=20.0, kind="solid"))],
        ]
        steps = [lambda e=e: store.apply_changeset("ka", e, who="test") for e in edits]
        steps.append(lambda: store.review_by_score("ka", accept_from=0.7, reject_below=0.4, who="test"))
        steps.append(lambda: store.revert_changeset("ka", store.changesets("ka")[0][0].id, who="test"))
        sizes = []
        for step in steps:
            step()
            counted = store.count_changes("ka", revision)
            updated, at, changes = updated_index(store, "ka", index, revision, coverage)
            anew = load_index(store, "ka", CRS, coverage)
            assert at == store.map_head("ka").revision and changes >= 1 and counted == changes
            np.testing.assert_array_equal(updated.key, anew.key)
            np.testing.assert_array_equal(updated.xy, anew.xy)
            np.testing.assert_array_equal(updated.weight, anew.weight)
            np.testing.assert_array_equal(updated.half_length, anew.half_length)
            np.testing.assert_array_equal(updated.axis, anew.axis)
            np.testing.assert_array_equal(updated.extent.squares, anew.extent.squares)
            assert all(a.equals_exact(b, 0.0) for a, b in zip(updated.extent.pieces, anew.extent.pieces))
            index, revision = updated, at
            sizes.append(len(index))
        # the review's rejections left the index, and its revert brought them back
        assert sizes[2] < sizes[1] == 819 + 60 - 1 + 1 == sizes[3]
        # more changes than an update is worth (here 100 at least, a tenth of the map): built anew
        from service import map_index

        monkeypatch.setattr(map_index, "UPDATE_MIN", 100)
        store.apply_changeset("ka", [Change("update", id=i, fields={"weight": 5.0}) for i in index.key[:100].tolist()],
                              who="test")  # fmt: skip
        assert updated_index(store, "ka", index, revision, coverage) is not None
        store.apply_changeset("ka", [Change("update", id=i, fields={"weight": 6.0}) for i in index.key[:101].tolist()],
                              who="test")  # fmt: skip
        with caplog.at_level(logging.INFO, logger="service.map_index"), monkeypatch.context() as unread:
            unread.setattr(store, "changes", lambda *a, **k: pytest.fail("the feed was read"))  # counted only
            assert updated_index(store, "ka", index, revision, coverage) is None
        assert f"more than 100 markings changed since revision {revision}; its index is built anew" in caplog.text
    finally:
        store.close()
