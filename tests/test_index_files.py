"""Built indexes kept in files (``service.index_files``), on a real SQLite store.

What a process that reads a kept index relies on: it is the index of the map
as the database holds it now (or, asked for, an older revision of the same
history), a file that is damaged, foreign or of another history is never
taken for one, and the folder stays within its size.
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from mapbuilder.model import Marking
from mapbuilder.store import Store
from service.index_files import IndexFiles, database_identity
from service.map_index import load_index

CRS = "EPSG:25832"


def _markings(n: int, x0: float = 457_000.0) -> list[Marking]:
    rng = np.random.default_rng(0)
    return [Marking(x=x0 + 3.0 * k, y=5_428_000.0 + rng.normal(0, 0.05), length_m=3.0, width_m=0.12,
                    bearing_deg=90.0, weight=40.0, kind="dash") for k in range(n)]  # fmt: skip


@pytest.fixture
def store(tmp_path):
    s = Store(f"sqlite:///{tmp_path / 'maps.sqlite'}")
    for map_id in ("a", "b", "c"):
        s.create_map(map_id, crs=CRS)
        s.add_markings(map_id, _markings(40))
    yield s
    s.close()


def _files(store, tmp_path, **kw) -> IndexFiles:
    kw.setdefault("min_markings", 1)
    return IndexFiles(tmp_path / "indexes", database_identity(store.engine.url), **kw)


def _built(store, map_id: str, coverage: str = "markings"):
    return store.map_head(map_id), load_index(store, map_id, CRS, coverage)


def test_a_kept_index_is_read_back_at_its_revision_and_only_by_this_user(store, tmp_path):
    files = _files(store, tmp_path)
    head, index = _built(store, "a")
    path = files.save("a", head, "markings", index)
    assert path is not None and path.parent == tmp_path / "indexes"
    assert os.stat(path).st_mode & 0o777 == 0o600 and os.stat(path.parent).st_mode & 0o777 == 0o700
    kept = files.load("a", store.map_head("a"), "markings")
    assert kept.revision == head.revision and len(kept.index) == len(index) == 40
    assert kept.index.extent.area.equals(index.extent.area) and kept.index.extent_rule == "markings"
    # by another coverage, of another map, from another database: nothing kept
    assert files.load("a", head, "hull") is None and files.load("b", store.map_head("b"), "markings") is None
    other = IndexFiles(files.directory, "sqlite:/elsewhere.sqlite", 1)
    assert other.load("a", head, "markings") is None
    # a file others may write is not read (a pickle runs what it holds)
    os.chmod(path, 0o664)
    assert files.load("a", head, "markings") is None
    os.chmod(path, 0o600)
    assert files.load("a", head, "markings") is not None


def test_an_edited_map_finds_its_older_index_and_the_next_save_replaces_it(store, tmp_path):
    files = _files(store, tmp_path)
    head, index = _built(store, "a")
    files.save("a", head, "markings", index)
    store.add_markings("a", _markings(5, x0=457_500.0))
    now = store.map_head("a")
    kept = files.load("a", now, "markings")
    assert kept.revision == head.revision < now.revision and len(kept.index) == 40  # the older one, said so
    _, newer = _built(store, "a")
    files.save("a", now, "markings", newer)
    assert [p.name.split("-r")[1][:10] for p in files.directory.glob("*.index")] == [f"{now.revision:010d}"]
    assert files.load("a", now, "markings").revision == now.revision


def test_a_file_of_another_history_of_the_database_is_deleted(store, tmp_path):
    """A database restored from a backup goes back to an older revision, and its edits then reach
    the revision numbers of the files kept before: those files are not its map's."""
    files = _files(store, tmp_path)
    head, index = _built(store, "a")
    newer = head._replace(revision=head.revision + 3, updated="2030-01-01 00:00:00")
    path = files.save("a", newer, "markings", index)
    assert files.load("a", head, "markings") is None and not path.exists()  # newer than the map
    path = files.save("a", newer, "markings", index)
    again = newer._replace(updated="2031-01-01 00:00:00")  # the same revision, written at another time
    assert files.load("a", again, "markings") is None and not path.exists()


def test_a_damaged_file_is_a_miss_and_goes(store, tmp_path, caplog):
    files = _files(store, tmp_path)
    head, index = _built(store, "a")
    path = files.save("a", head, "markings", index)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    assert files.load("a", head, "markings") is None
    assert not path.exists() and "cannot be read back" in caplog.text
    path.write_bytes(b"not a pickle")
    os.chmod(path, 0o600)
    assert files.load("a", head, "markings") is None and not path.exists()


def test_small_indexes_are_not_kept_and_a_folder_that_cannot_be_written_is_only_logged(store, tmp_path, caplog):
    head, index = _built(store, "a")
    assert _files(store, tmp_path, min_markings=41).save("a", head, "markings", index) is None
    (tmp_path / "blocked").write_text("a file where the folder would be")
    blocked = IndexFiles(tmp_path / "blocked", "db", 1)
    assert blocked.save("a", head, "markings", index) is None and "could not be kept" in caplog.text
    assert blocked.load("a", head, "markings") is None


def test_the_folder_keeps_within_its_size_least_recently_used_first(store, tmp_path):
    files = _files(store, tmp_path)
    sizes = {}
    for map_id in ("a", "b"):
        head, index = _built(store, map_id)
        sizes[map_id] = files.save(map_id, head, "markings", index).stat().st_size
    time.sleep(0.02)
    assert files.load("a", store.map_head("a"), "markings") is not None  # "a" used after "b"
    files.max_bytes = sizes["a"] + sizes["b"] + sizes["a"] // 2
    head, index = _built(store, "c")
    files.save("c", head, "markings", index)
    assert files.load("b", store.map_head("b"), "markings") is None  # the least recently used went
    assert files.load("a", store.map_head("a"), "markings") is not None
    assert files.load("c", head, "markings") is not None
    # the locks of builds: one used today stays, one unused for a day goes with the next save
    with files.building("a", store.map_head("a"), "markings"):
        pass
    with files.building("b", store.map_head("b"), "markings"):
        pass
    old, used = sorted(files.directory.glob("*.lock"))[:2]
    os.utime(old, (time.time() - 2 * 86_400, time.time() - 2 * 86_400))
    files.save("c", store.map_head("c"), "hull", load_index(store, "c", CRS, "hull"))
    assert not old.exists() and used.exists()


def test_an_sqlite_database_is_the_same_from_any_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    here = database_identity("sqlite:///maps.sqlite")
    assert here == database_identity(f"sqlite:///{tmp_path / 'maps.sqlite'}")
    (tmp_path / "sub").mkdir()
    monkeypatch.chdir(tmp_path / "sub")
    assert database_identity("sqlite:///maps.sqlite") != here
    url = "postgresql://lanemap:secret@db:5432/lanemap"
    assert database_identity(url) == "postgresql://lanemap:***@db:5432/lanemap"  # no secret in a key


def test_a_build_under_way_in_one_process_holds_the_next(store, tmp_path):
    """Two builders of the same map (the workers of one server, at its start): the second waits
    for the first's file and reads it instead of building the index again."""
    files = _files(store, tmp_path)
    head, index = _built(store, "a")
    inside, order = threading.Event(), []

    def first():
        with files.building("a", head, "markings"):
            inside.set()
            time.sleep(0.3)
            files.save("a", head, "markings", index)
            order.append("first saved")

    def second():
        inside.wait(5)
        with files.building("a", head, "markings"):
            order.append("second in")
            kept = files.load("a", head, "markings")
            order.append("found" if kept is not None else "missed")

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert order == ["first saved", "second in", "found"]
    with files.building("b", store.map_head("b"), "markings"):  # another map's builds do not wait
        assert files.load("a", head, "markings") is not None


def test_a_deleted_maps_kept_indexes_go_with_it(store, tmp_path):
    files = _files(store, tmp_path)
    for map_id in ("a", "b"):
        for coverage in ("hull", "markings"):
            head, index = _built(store, map_id, coverage)
            files.save(map_id, head, coverage, index)
            with files.building(map_id, head, coverage):
                pass
    files.forget("a", store.map_head("a").created)
    left = sorted(p.name for p in files.directory.iterdir())
    assert len(left) == 4 and files.load("b", store.map_head("b"), "hull") is not None  # b's two files, two locks
    assert files.load("a", store.map_head("a"), "hull") is None and files.load("a", store.map_head("a"), "markings") is None


def test_a_kept_index_too_far_behind_is_not_read_before_building(store, tmp_path, monkeypatch):
    """``current_index`` counts the changes since the newest kept file before reading it, against
    the update's cap, a share of the indexed markings: a map of many rejected markings (not in
    its index) caps its updates lower than its count, and the file is not read only to be
    refused."""
    from service import map_index
    from service.index_files import current_index

    monkeypatch.setattr(map_index, "UPDATE_MIN", 1)
    store.create_map("r", crs=CRS)
    store.add_markings("r", _markings(100))
    store.bulk_load("r", (Marking(x=457_000.0 + 3.0 * k, y=5_428_050.0, length_m=3.0, width_m=0.12, weight=40.0,
                                  status="rejected") for k in range(400)))  # fmt: skip
    files = _files(store, tmp_path)
    first = current_index(store, "r", CRS, "markings", files)
    assert len(first) == 100 and files.newest_revision("r", store.map_head("r"), "markings") is not None
    reads = []
    read = IndexFiles._read
    monkeypatch.setattr(IndexFiles, "_read", lambda self, path, *a: reads.append(path) or read(self, path, *a))
    # 20 changes: over a tenth of the 100 indexed, under a tenth of the 500 in the map
    store.add_markings("r", _markings(20, x0=458_000.0))
    built = []
    index = current_index(store, "r", CRS, "markings", files, on_build=built.append)
    assert len(index) == 120 and built == [520] and not reads
    # 5 more: within the cap, the file just kept is read and updated
    store.add_markings("r", _markings(5, x0=459_000.0))
    index = current_index(store, "r", CRS, "markings", files, on_build=built.append)
    assert len(index) == 125 and built == [520] and len(reads) == 1
