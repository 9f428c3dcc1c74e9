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
    result = race(api.base_url, api.token, map_id, ids, clients=20, duration=4.0, seed=1)
    problems = verify(api.base_url, map_id, ids, result)
    assert not problems, "\n".join(problems)
    # the race was real: writes were both accepted and rejected, of every kind
    assert len(result.accepted) >= 20
    assert result.count("412") > 0 and result.count("409") > 0
    assert {k for k, _ in result.answers} == {"patch", "put", "changeset"}
    assert "Traceback" not in api.log()
