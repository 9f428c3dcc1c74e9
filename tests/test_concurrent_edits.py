"""20 clients editing the same features with If-Match against a real server: no lost update.

The short version of ``benchmarks/concurrent_edits.py``, on SQLite and on
PostgreSQL; see ``tests/_edit_race.py`` for the writes and the invariants.
"""

from __future__ import annotations

import pytest

from tests._api_helpers import shared_server
from tests._edit_race import create_features, race, verify


@pytest.mark.parametrize("kind", ["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def test_concurrent_conditional_edits_lose_nothing(kind):
    api = shared_server(kind)
    map_id = api.new_map(prefix="race")
    with api.client(headers=api.auth) as c:
        ids = create_features(c, map_id, 4)
    result = race(api.base_url, api.token, map_id, ids, clients=20, duration=4.0, seed=1,
                  min_accepted=20)
    problems = verify(api.base_url, map_id, ids, result)
    assert not problems, "\n".join(problems)
    # the race was real: writes were both accepted and rejected, of every kind
    assert len(result.accepted) >= 20
    assert result.count("412") > 0 and result.count("409") > 0
    assert {k for k, _ in result.answers} == {"patch", "put", "changeset"}
    assert "Traceback" not in api.log()


def test_a_changeset_result_is_what_that_changeset_wrote(store):
    """Answers to a write (body, ETag) come from the write itself, not from a later read.

    Under concurrent edits on PostgreSQL a PATCH was once answered with the
    version another client wrote just after it; the store's result now carries
    the markings as this changeset left them.
    """
    from mapbuilder.model import Marking
    from mapbuilder.store import Change

    store.create_map("m", "m", "EPSG:25832")
    created = store.apply_changeset("m", [Change("create", marking=Marking(x=457900.0, y=5427900.0,
                                                                           weight=10.0, extra={"w": "a"}))],
                                    "a")  # fmt: skip
    mid = created.results[0]["id"]
    first = store.apply_changeset("m", [Change("update", id=mid, version=1, fields={"weight": 11.0})], "a")
    store.apply_changeset("m", [Change("update", id=mid, version=2, fields={"weight": 12.0})], "b")
    mine = first.markings[mid]
    assert (mine.id, mine.version, mine.weight, mine.extra) == (mid, 2, 11.0, {"w": "a"})
    assert created.markings[mid].version == 1 and created.markings[mid].weight == 10.0
    now = store.get_marking("m", mid)
    assert (now.version, now.weight) == (3, 12.0)
    # apart from version and weight, the result is the stored marking
    for name in ("x", "y", "lon", "lat", "length_m", "width_m", "bearing_deg", "kind", "source", "status",
                 "tile_key"):
        assert getattr(mine, name) == getattr(now, name), name
