"""``lanemap db copy``: a whole database into another, SQLite to PostgreSQL and back, ids kept."""

from __future__ import annotations

import os
import subprocess
import sys
from datetime import UTC

import pytest
import shapely
from sqlalchemy import select

from mapbuilder.dbcopy import TABLES, CopyError, copy_database
from mapbuilder.model import Marking
from mapbuilder.store import Change, Store

E0, N0 = 457000.0, 5428000.0  # Karlsruhe, EPSG:25832


def _m(dx: float, **kw) -> Marking:
    return Marking(x=E0 + dx, y=N0, length_m=3.0, width_m=0.12, weight=36, **kw)


def _fill(store: Store) -> None:
    """Two maps with every kind of history: imports, edits, deletes, a revert, a build job
    whose tiles were built twice, imagery; the last marking created is deleted again, so that
    the highest id given out is no longer in the markings table."""
    store.create_map("ka", "Karlsruhe", crs="EPSG:25832")
    store.create_map("empty", crs="EPSG:32632")
    ids = store.add_markings("ka", [_m(3.0 * k, kind="dash", extra={"lane": k}) for k in range(20)], who="alice")
    res = store.apply_changeset("ka", [
        Change("update", id=ids[0], fields={"status": "accepted"}),
        Change("delete", id=ids[1]),
        Change("create", marking=_m(100.0, kind="stop_line")),
    ], who="bob", comment="review")  # fmt: skip
    store.revert_changeset("ka", res.changeset_id, who="alice")
    job = store.create_job("build", "ka", {"imagery": "1"})
    store.replace_detected("ka", "t0", [_m(200.0 + k) for k in range(5)], job_id=job)
    store.replace_detected("ka", "t0", [_m(200.2 + k) for k in range(5)], job_id=job,
                           ground=shapely.to_wkb(shapely.box(E0, N0, E0 + 100, N0 + 100)))
    store.update_job(job, status="successful", progress=100.0)
    store.add_imagery("ka", "/srv/imagery/ka.tif", "EPSG:25832", (E0, N0, E0 + 100, N0 + 100), 0.1)
    last = store.apply_changeset("ka", [Change("create", marking=_m(300.0))], who="bob").results[0]["id"]
    store.apply_changeset("ka", [Change("delete", id=last)], who="bob")


def _rows(store: Store) -> dict[str, list[tuple]]:
    """Every row of every table, in key order, timestamps as UTC instants."""
    out = {}
    with store.snapshot() as conn:
        for t in TABLES:
            rows = []
            for r in conn.execute(select(t).order_by(*t.primary_key.columns)):
                rows.append(tuple(
                    (v.replace(tzinfo=UTC) if v.tzinfo is None else v.astimezone(UTC))
                    if hasattr(v, "tzinfo") else v for v in r))  # fmt: skip
            out[t.name] = rows
    return out


@pytest.mark.parametrize("direction", ["sqlite-to-postgresql", "postgresql-to-sqlite"])
def test_a_copy_holds_every_row_and_goes_on_giving_new_ids(direction, tmp_path, postgres_url):
    sqlite_url = f"sqlite:///{tmp_path / 'lanemap.sqlite'}"
    src_url, dst_url = (sqlite_url, postgres_url) if direction.startswith("sqlite") else (postgres_url, sqlite_url)
    source, target = Store(src_url), Store(dst_url)
    _fill(source)
    seen = []
    report = copy_database(source, target, batch=7, progress=lambda t, done, total: seen.append((t, done, total)))
    before = _rows(source)
    assert _rows(target) == before
    assert report.rows == {name: len(rows) for name, rows in before.items()}
    assert report.rows["markings"] == 25 and report.rows["removed_markings"] == 7 and report.rows["job_tiles"] == 1
    assert report.rows["imaged_ground"] == 1 and target.imaged_footprint("ka").equals(source.imaged_footprint("ka"))
    assert ("markings", 25, 25) in seen and ("markings", 7, 25) in seen  # batch by batch
    # The copy is a working store: the change feed reads the same, and new ids continue past
    # every id the source gave out (the deleted last marking's included).
    for map_id in ("ka", "empty"):
        a, b = source.changes(map_id, 0), target.changes(map_id, 0)
        assert [(r, m.id, m.version) for r, m in a.changed] == [(r, m.id, m.version) for r, m in b.changed]
        assert a.removed == b.removed and a.revision == b.revision
    highest = max([r[1] for r in before["removed_markings"]] + [m[0] for m in before["markings"]])
    assert highest not in {m[0] for m in before["markings"]}  # the last id given out is a deleted one
    new = target.apply_changeset("ka", [Change("create", marking=_m(400.0))], who="carol")
    assert new.results[0]["id"] > highest and new.changeset_id > max(r[0] for r in before["changesets"])
    assert target.create_job("build", "ka", {}) > max(r[0] for r in before["jobs"])
    # a target that holds data is refused and left as it was
    held = _rows(target)
    with pytest.raises(CopyError, match="not empty"):
        copy_database(source, target)
    assert _rows(target) == held
    with pytest.raises(CopyError, match="same database"):
        copy_database(source, Store(src_url))
    source.close()
    target.close()


def test_db_copy_command_makes_a_backup_file(tmp_path):
    """``lanemap db copy sqlite:///backup.sqlite``: one line naming what was copied, and the
    backup serves the same maps; a second copy into it is refused with one line."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("LANEMAP_")}
    env.update(LANEMAP_DATABASE_URL=f"sqlite:///{tmp_path / 'live.sqlite'}", LANEMAP_DATA_DIR=str(tmp_path / "data"))
    _fill(Store(env["LANEMAP_DATABASE_URL"]))

    def lanemap(*args, **extra):
        return subprocess.run([sys.executable, "-m", "service.cli", *args], env={**env, **extra}, cwd=tmp_path,
                              capture_output=True, text=True, timeout=120)  # fmt: skip

    backup = f"sqlite:///{tmp_path / 'backup.sqlite'}"
    proc = lanemap("db", "copy", backup)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("copied 2 maps, 25 markings, 5 changesets,") and "backup.sqlite" in proc.stdout
    listed = lanemap("maps", "list", LANEMAP_DATABASE_URL=backup)
    assert listed.stdout == lanemap("maps", "list").stdout and "Karlsruhe" in listed.stdout
    again = lanemap("db", "copy", backup)
    assert again.returncode == 1 and again.stderr.strip().splitlines() == [
        "error: the target database is not empty (table maps holds 2 rows): copy into a new one"]
    nowhere = lanemap("db", "copy", f"sqlite:///{tmp_path / 'b2.sqlite'}", "--from", f"sqlite:///{tmp_path / 'no.sqlite'}")
    assert nowhere.returncode == 1 and "no database at" in nowhere.stderr and not (tmp_path / "no.sqlite").exists()
