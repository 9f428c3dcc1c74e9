"""Atomic changesets, history and revert, and concurrent edits, over HTTP on SQLite and PostgreSQL."""

from __future__ import annotations

import threading

import httpx
import pytest

from tests._api_helpers import feature, shared_server
from tests.test_api_features import assert_problem


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def api(request):
    return shared_server(request.param)


def _seed(api, n=3):
    map_id = api.new_map()
    with api.client(headers=api.auth) as c:
        ids = []
        for i in range(n):
            r = c.post(f"/collections/{map_id}/items", json=feature(8.428 + i * 1e-4, 49.0071, weight=10 + i))
            assert r.status_code == 201
            ids.append(r.json()["id"])
    return map_id, ids


def _state(c, map_id):
    fc = c.get(f"/collections/{map_id}/items?limit=10000").json()
    return {f["id"]: (f["properties"]["weight"], f["properties"]["status"], f["properties"]["version"])
            for f in fc["features"]}  # fmt: skip


def test_changeset_applies_all_changes_and_logs_them(api):
    map_id, (a, b, c_) = _seed(api)
    body = {
        "comment": "review of block 7",
        "changes": [
            {"op": "create", "feature": feature(8.4285, 49.0072, weight=77, kind="dash")},
            {"op": "update", "id": a, "version": '"1"', "patch": {"properties": {"status": "accepted"}}},
            {"op": "update", "id": b, "patch": {"properties": {"weight": 99}}},
            {"op": "delete", "id": c_, "version": "1"},
        ],
    }
    with api.client(headers=api.auth) as c:
        r = c.post(f"/collections/{map_id}/changesets", json=body)
        assert r.status_code == 201, r.text
        res = r.json()
        ops = [x["op"] for x in res["results"]]
        assert ops == ["create", "update", "update", "delete"]
        new_id = res["results"][0]["id"]
        assert res["results"][1] == {"op": "update", "id": a, "version": "2"}
        # the returned versions are the features' ETags
        assert c.get(f"/collections/{map_id}/items/{a}").headers["etag"] == '"2"'
        state = _state(c, map_id)
        assert state[new_id][0] == 77 and state[a][1] == "accepted" and state[b][0] == 99 and c_ not in state
        hist = c.get(f"/collections/{map_id}/history", params={"changeset": res["changeset"]}).json()
        assert hist["numberMatched"] == 4
        by_op = {}
        for e in hist["edits"]:
            by_op.setdefault(e["op"], []).append(e)
            assert e["comment"] == "review of block 7" and e["who"] == "api" and e["at"]
        assert by_op["delete"][0]["before"]["weight"] == 12 and by_op["delete"][0]["after"] is None
        upd = {e["feature_id"]: e for e in by_op["update"]}
        assert upd[b]["before"]["weight"] == 11 and upd[b]["after"]["weight"] == 99
        cs = c.get(f"/collections/{map_id}/changesets/{res['changeset']}").json()
        assert (cs["created"], cs["updated"], cs["deleted"]) == (1, 2, 1) and len(cs["edits"]) == 4
        listed = c.get(f"/collections/{map_id}/changesets").json()
        assert listed["changesets"][0]["id"] == res["changeset"]


def test_changeset_with_a_stale_version_changes_nothing(api):
    map_id, (a, b, c_) = _seed(api)
    with api.client(headers=api.auth) as c:
        assert c.patch(f"/collections/{map_id}/items/{b}", json={"properties": {"weight": 5}}).status_code == 200
        before = _state(c, map_id)
        body = {"changes": [
            {"op": "create", "feature": feature(8.4285, 49.0072)},
            {"op": "update", "id": a, "version": "1", "patch": {"properties": {"weight": 1}}},
            {"op": "update", "id": b, "version": "1", "patch": {"properties": {"weight": 2}}},
            {"op": "delete", "id": c_, "version": "1"},
            {"op": "delete", "id": "999999", "version": "1"},
        ]}  # fmt: skip
        r = c.post(f"/collections/{map_id}/changesets", json=body)
        problem = assert_problem(r, 409)
        assert set(problem["conflicting_ids"]) == {b, "999999"}
        reasons = {x["id"]: x["reason"] for x in problem["conflicts"]}
        assert reasons == {b: "version", "999999": "missing"}
        assert _state(c, map_id) == before
        hist = c.get(f"/collections/{map_id}/history").json()
        assert hist["numberMatched"] == 4  # three creates and the one patch


@pytest.mark.parametrize("change, words", [
    ({"op": "move", "id": "1"}, "changes.0.op"),
    ({"op": "update", "patch": {}}, "changes[0].id"),
    ({"op": "update", "id": "1"}, "changes[0].patch"),
    ({"op": "create"}, "changes[0].feature"),
    ({"op": "delete", "id": "x1"}, "changes[0].id"),
    ({"op": "delete", "id": "1", "version": "v1"}, "changes[0].version"),
    ({"op": "create", "feature": {"type": "Feature", "geometry": None}}, "changes[0].feature"),
])  # fmt: skip
def test_malformed_changes_name_the_change(api, change, words):
    map_id, _ = _seed(api, 1)
    with api.client(headers=api.auth) as c:
        r = c.post(f"/collections/{map_id}/changesets", json={"changes": [change]})
        assert_problem(r, 422, words)
        assert c.get(f"/collections/{map_id}/history").json()["numberMatched"] == 1
        assert_problem(c.post(f"/collections/{map_id}/changesets", json={"changes": []}), 422, "changes")


def test_revert_changeset_restores_the_map(api):
    map_id, (a, b, c_) = _seed(api)
    with api.client(headers=api.auth) as c:
        before = {k: v[:2] for k, v in _state(c, map_id).items()}
        body = {"changes": [
            {"op": "create", "feature": feature(8.4285, 49.0072)},
            {"op": "update", "id": a, "patch": {"properties": {"weight": 1, "status": "rejected"}}},
            {"op": "delete", "id": c_},
        ]}  # fmt: skip
        cs = c.post(f"/collections/{map_id}/changesets", json=body).json()["changeset"]
        r = c.post(f"/collections/{map_id}/changesets/{cs}/revert", json={"comment": "undo"})
        assert r.status_code == 201, r.text
        after = {k: v[:2] for k, v in _state(c, map_id).items()}
        assert after == before  # same ids (the deleted one is back under its id), same values
        revert = c.get(f"/collections/{map_id}/changesets/{r.json()['changeset']}").json()
        assert revert["reverts"] == cs and revert["comment"] == "undo"
        # reverting again meets the restored markings: a conflict, not a server error
        again = c.post(f"/collections/{map_id}/changesets/{cs}/revert")
        assert_problem(again, 409)
        assert {k: v[:2] for k, v in _state(c, map_id).items()} == before
        assert_problem(c.post(f"/collections/{map_id}/changesets/424242/revert"), 404, "424242")


def test_revert_one_edit(api):
    map_id, (a, b, _) = _seed(api)
    with api.client(headers=api.auth) as c:
        c.patch(f"/collections/{map_id}/items/{a}", json={"properties": {"weight": 500}})
        c.patch(f"/collections/{map_id}/items/{b}", json={"properties": {"weight": 600}})
        edits = c.get(f"/collections/{map_id}/history", params={"feature": a}).json()["edits"]
        edit = next(e for e in edits if e["op"] == "update")
        r = c.post(f"/collections/{map_id}/history/{edit['id']}/revert")
        assert r.status_code == 201, r.text
        state = _state(c, map_id)
        assert state[a][0] == 10 and state[b][0] == 600
        assert_problem(c.post(f"/collections/{map_id}/history/{edit['id']}/revert"), 409)
        assert_problem(c.post(f"/collections/{map_id}/history/987654/revert"), 404)


def test_concurrent_if_match_edits_one_wins(api):
    map_id, (a, *_rest) = _seed(api, 1)
    results = []
    barrier = threading.Barrier(4)

    def edit(i):
        with httpx.Client(base_url=api.base_url, headers=api.auth, timeout=60) as c:
            barrier.wait()
            r = c.patch(f"/collections/{map_id}/items/{a}", json={"properties": {"weight": 100 + i}},
                        headers={"If-Match": '"1"'})  # fmt: skip
            results.append((i, r.status_code))

    threads = [threading.Thread(target=edit, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    codes = sorted(code for _, code in results)
    assert codes == [200, 412, 412, 412], results
    winner = next(i for i, code in results if code == 200)
    with api.client() as c:
        f = c.get(f"/collections/{map_id}/items/{a}")
        assert f.headers["etag"] == '"2"' and f.json()["properties"]["weight"] == 100 + winner


def test_concurrent_patches_without_if_match_lose_nothing(api):
    map_id, (a, *_rest) = _seed(api, 1)
    barrier = threading.Barrier(2)
    codes = []

    def edit(prop, value):
        with httpx.Client(base_url=api.base_url, headers=api.auth, timeout=60) as c:
            barrier.wait()
            codes.append(c.patch(f"/collections/{map_id}/items/{a}", json={"properties": {prop: value}}).status_code)

    t1 = threading.Thread(target=edit, args=("status", "accepted"))
    t2 = threading.Thread(target=edit, args=("kind", "stop_line"))
    t1.start(), t2.start(), t1.join(), t2.join()
    assert codes == [200, 200]
    with api.client() as c:
        props = c.get(f"/collections/{map_id}/items/{a}").json()["properties"]
    assert props["status"] == "accepted" and props["kind"] == "stop_line" and props["version"] == 3


def test_many_concurrent_writers_lose_nothing(api):
    """Eight clients edit and create at once: no server error, every change lands exactly once."""
    map_id, ids = _seed(api, 8)
    errors = []

    def work(k):
        with httpx.Client(base_url=api.base_url, headers=api.auth, timeout=120) as c:
            for i in range(10):
                r = c.patch(f"/collections/{map_id}/items/{ids[k]}", json={"properties": {"weight": 1000 + i}})
                if r.status_code != 200:
                    errors.append(r.text)
                r = c.post(f"/collections/{map_id}/changesets", json={"changes": [
                    {"op": "create", "feature": feature(8.43 + k * 1e-4, 49.0 + i * 1e-5, worker=k, i=i)}]})  # fmt: skip
                if r.status_code != 201:
                    errors.append(r.text)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    with api.client() as c:
        state = _state(c, map_id)
        assert len(state) == 8 + 80
        for k in range(8):
            assert state[ids[k]][0] == 1009 and state[ids[k]][2] == 11
        created = c.get(f"/collections/{map_id}/items?limit=1000").json()["features"]
        tags = {(f["properties"].get("worker"), f["properties"].get("i")) for f in created}
        assert {(k, i) for k in range(8) for i in range(10)} <= tags
        assert c.get(f"/collections/{map_id}/history").json()["numberMatched"] == 8 + 80 + 80


def _follow(c, map_id, since, **params):
    """Apply every page of ``/changes`` since ``since`` to a fresh dict; (copy, revision, pages)."""
    copy, url, pages, listed, total = {}, f"/collections/{map_id}/changes", 0, 0, None
    query = {"since": since, **params}
    while True:
        r = c.get(url, params=query)
        assert r.status_code == 200 and r.headers["content-type"].startswith("application/geo+json"), r.text
        page = r.json()
        pages += 1
        listed += page["numberReturned"]
        # the first page says how many the pages hold in all (nothing is written meanwhile here)
        assert (pages == 1) == ("numberMatched" in page)
        total = page.get("numberMatched", total)
        for gone in page["removed"]:
            copy[gone["id"]] = None
        for f in page["features"]:
            assert f["properties"]["revision"] > since
            copy[f["id"]] = (f["properties"]["weight"], f["properties"]["status"], f["properties"]["version"])
        nxt = [ln["href"] for ln in page["links"] if ln["rel"] == "next"]
        if not nxt:
            assert listed == total == len(copy), (listed, total, len(copy))
            return copy, page["revision"], pages
        url, query = nxt[0], None


def test_a_copy_follows_the_map_through_its_changes(api):
    """``GET /collections/{id}/changes?since=``: a copy applies the pages and holds what the map
    holds; a fleet's copy (status filter) drops a rejected marking; paging by ``next`` links."""
    map_id, ids = _seed(api, n=5)
    with api.client(headers=api.auth) as c:
        assert c.get(f"/collections/{map_id}").json()["changesSince"] == 0  # nothing pruned: any copy follows
        href = [ln["href"] for ln in c.get(f"/collections/{map_id}").json()["links"] if ln["rel"] == "changes"]
        feed = c.get(href[0]).json()
        assert len(href) == 1 and feed["since"] == 0  # the map links to its feed
        # a copy learns the metric CRS the map keeps its markings in
        assert feed["storageCrs"] == c.get(f"/collections/{map_id}").json()["storageCrs"] is not None
        first, rev0, _ = _follow(c, map_id, 0)
        assert {k for k, v in first.items() if v} == set(ids) and rev0 == c.get(f"/collections/{map_id}").json()["revision"]
        r = c.post(f"/collections/{map_id}/changesets", json={"comment": "c", "changes": [
            {"op": "update", "id": ids[0], "patch": {"properties": {"status": "rejected"}}},
            {"op": "delete", "id": ids[1]},
            {"op": "create", "feature": feature(8.4291, 49.0071, weight=7)}]})  # fmt: skip
        assert r.status_code == 201, r.text
        delta, rev1, _ = _follow(c, map_id, rev0)
        assert rev1 == rev0 + 1
        assert delta[ids[1]] is None and delta[ids[0]][1] == "rejected" and len(delta) == 3
        copy = {k: v for k, v in first.items()}
        copy.update(delta)
        assert {k: v for k, v in copy.items() if v} == _state(c, map_id)
        fleet, _, _ = _follow(c, map_id, rev0, status="accepted,unreviewed")
        assert fleet[ids[0]] is None and fleet[ids[1]] is None
        paged, rev, pages = _follow(c, map_id, 0, limit=2)
        assert pages == 3 and rev == rev1 and {k: v for k, v in paged.items() if v} == _state(c, map_id)
        assert _follow(c, map_id, rev1)[0] == {}
        # a revision the map never reached, and bad parameters, are problems
        assert_problem(c.get(f"/collections/{map_id}/changes", params={"since": rev1 + 1}), 409, "older backup")
        assert_problem(c.get(f"/collections/{map_id}/changes", params={"since": -1}), 422)
        assert_problem(c.get(f"/collections/{map_id}/changes"), 422, "since")
        assert_problem(c.get(f"/collections/{map_id}/changes", params={"since": 0, "after": "x"}), 400, "REVISION:ID")
        assert_problem(c.get(f"/collections/{map_id}/changes", params={"since": 0, "status": "gone"}), 400)
        assert_problem(c.get("/collections/no-such-map/changes", params={"since": 0}), 404)


def test_detections_are_accepted_and_rejected_by_score_over_http(api):
    """``POST /collections/{id}/review``: a dry run counts (200, nothing written); the review is one
    changeset (201 with its Location) in the history; bad thresholds are problems; a revert undoes it."""
    map_id = api.new_map(prefix="review")
    scores = [0.02, 0.3, 0.6, 0.93, 0.99]
    feats = [feature(8.428 + k * 1e-4, 49.0071, source="detected", score=s) for k, s in enumerate(scores)]
    with api.client(headers=api.auth) as c:
        assert c.post(f"/collections/{map_id}/import", json={"type": "FeatureCollection", "features": feats}).status_code == 201
        before = _state(c, map_id)
        url = f"/collections/{map_id}/review"
        dry = c.post(url, json={"accept_from": 0.9, "reject_below": 0.1, "dry_run": True})
        assert dry.status_code == 200 and (dry.json()["accepted"], dry.json()["rejected"], dry.json()["changeset"]) == (2, 1, None)
        assert _state(c, map_id) == before
        box = "8.4279,49.007,8.42825,49.0072"  # the first three only
        r = c.post(url, json={"accept_from": 0.9, "reject_below": 0.1, "bbox": box})
        assert r.status_code == 201 and (r.json()["accepted"], r.json()["rejected"]) == (0, 1), r.text
        rejected = {k for k, v in _state(c, map_id).items() if v[1] == "rejected"}
        assert len(rejected) == 1
        r = c.post(url, json={"accept_from": 0.9, "comment": "sure ones"})
        assert r.status_code == 201, r.text
        body = r.json()
        assert (body["accepted"], body["rejected"]) == (2, 0) and r.headers["location"].endswith(f"/changesets/{body['changeset']}")
        cs = c.get(r.headers["location"]).json()
        assert (cs["comment"], cs["updated"]) == ("sure ones", 2)
        accepted = {k for k, v in _state(c, map_id).items() if v[1] == "accepted"}
        assert len(accepted) == 2 and all(before[k][2] + 1 == _state(c, map_id)[k][2] for k in accepted)
        assert_problem(c.post(url, json={"accept_from": 0.5, "reject_below": 0.7}), 400, "above accept_from")
        assert_problem(c.post(url, json={}), 400, "give accept_from")
        assert_problem(c.post(url, json={"accept_from": 2}), 422, "accept_from")
        assert_problem(c.post(url, json={"accept_from": 0.5, "bbox": "1,2,3"}), 422, "bbox")
        assert_problem(c.post("/collections/no-such-map/review", json={"accept_from": 0.5}), 404)
        assert c.post(f"/collections/{map_id}/changesets/{body['changeset']}/revert").status_code == 201
        after = {k: v[1] for k, v in _state(c, map_id).items()}
        assert after == {k: "rejected" if k in rejected else "unreviewed" for k in before}
    with api.client() as c:  # no token: no write
        assert_problem(c.post(url, json={"accept_from": 0.5}), 401)


def test_the_review_queue_goes_on_past_detections_decided_meanwhile(api):
    """``GET /collections/{id}/review/queue``: the unreviewed detections lowest score first (ties by
    id, those without a score last), a page at a time; a page's ``next`` link goes on after its last
    detection, so that the detections decided between two pages move nothing; people's markings and
    decided ones are not in it; a box narrows it; a bad ``after`` is a 400 problem."""
    map_id = api.new_map(prefix="queue")
    scores = [0.7, 0.2, None, 0.5, 0.2, 0.9, 0.05, None, 0.5, 0.31, 0.6]
    feats = [feature(8.428 + k * 1e-4, 49.0071, source="detected", score=s) for k, s in enumerate(scores)]
    feats += [feature(8.428, 49.0075, source="manual", score=0.01),
              feature(8.4281, 49.0075, source="detected", score=0.01, status="rejected")]  # fmt: skip
    with api.client(headers=api.auth) as c:
        assert c.post(f"/collections/{map_id}/import", json={"type": "FeatureCollection", "features": feats}).status_code == 201
        ids = sorted(int(k) for k, v in _state(c, map_id).items())[:len(scores)]
        key = {i: (s is None, s or 0.0, i) for i, s in zip(ids, scores)}
        want = [str(i) for i in sorted(ids, key=key.get)]
        url = f"/collections/{map_id}/review/queue"
        first = c.get(url, params={"limit": 4})
        assert first.status_code == 200 and first.headers["content-type"].startswith("application/geo+json")
        page = first.json()
        assert [f["id"] for f in page["features"]] == want[:4] and page["numberMatched"] == len(scores)
        # two detections of the page and one further on are decided before the next page is read:
        # the queue skips none (an offset would skip two) and loses the one decided
        decided = [want[0], want[1], want[6]]
        for fid in decided:
            f = c.get(f"/collections/{map_id}/items/{fid}")
            r = c.patch(f"/collections/{map_id}/items/{fid}", json={"properties": {"status": "accepted"}},
                        headers={"If-Match": f.headers["etag"], "Content-Type": "application/merge-patch+json"})  # fmt: skip
            assert r.status_code == 200, r.text
        got = [f["id"] for f in page["features"]]
        for _ in range(len(scores)):  # a queue that did not go on would loop
            nxt = [ln["href"] for ln in page["links"] if ln["rel"] == "next"]
            if not nxt:
                break
            page = c.get(nxt[0]).json()
            got += [f["id"] for f in page["features"]]
        assert got == [i for i in want if i != want[6]]
        assert page["numberMatched"] == len(scores) - 3
        # within a box: those of the first four detections not decided
        box = c.get(url, params={"bbox": "8.4279,49.007,8.42835,49.0072"}).json()
        inside = [str(i) for i in sorted(ids[:4], key=key.get) if str(i) not in decided]
        assert [f["id"] for f in box["features"]] == inside and len(inside) == 3
        assert box["numberMatched"] == 3 and not [ln for ln in box["links"] if ln["rel"] == "next"]
        for bad in ("0.5", "x,3", "nan,3", "0.5,-1", "0.5,0", "inf,2", "0.5,99999999999999999999"):
            assert_problem(c.get(url, params={"after": bad}), 400, "after")
        assert_problem(c.get(url, params={"bbox": "1,2,3"}), 400, "bbox")
        assert_problem(c.get("/collections/no-such-map/review/queue"), 404)
