"""OGC API Features (Part 1 read, Part 4 edit) against a real uvicorn server, on SQLite and PostgreSQL."""

from __future__ import annotations

import json
import math
import time

import httpx
import pytest

from mapbuilder.crs import to_wgs84
from mapbuilder.geojson import markings_to_feature_collection
from mapbuilder.lanelet2 import layout_markings, read_lanelet2
from tests._api_helpers import SHARED_DATA, feature, shared_server

KARLSRUHE_OSM = SHARED_DATA / "karlsruhe-lanelet2" / "mapping_example.osm"
PROBLEM = "application/problem+json"


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def api(request):
    return shared_server(request.param)


@pytest.fixture(scope="module")
def karlsruhe_fc():
    items = layout_markings(read_lanelet2(KARLSRUHE_OSM, crs="EPSG:25832"))
    tr = to_wgs84("EPSG:25832")
    for m in items:
        m.lon, m.lat = tr.transform(m.x, m.y)
    return markings_to_feature_collection(items)


@pytest.fixture(scope="module")
def imported(api, karlsruhe_fc):
    map_id = api.new_map(prefix="ka")
    r = httpx.post(f"{api.base_url}/collections/{map_id}/import", json=karlsruhe_fc, headers=api.auth, timeout=60)
    assert r.status_code == 201, r.text
    return map_id, r.json()


def assert_problem(r: httpx.Response, status: int, *words: str) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM)
    body = r.json()
    assert body["status"] == status and body["type"] and body["title"] and body["detail"]
    for w in words:
        assert w in body["detail"], body
    return body


def test_landing_conformance_and_openapi(api):
    with api.client() as c:
        landing = c.get("/").json()
        rels = {link["rel"] for link in landing["links"]}
        assert {"self", "service-desc", "conformance", "data", "localize"} <= rels
        conf = c.get("/conformance").json()["conformsTo"]
        assert "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/core" in conf
        assert "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/geojson" in conf
        assert "http://www.opengis.net/spec/ogcapi-features-4/1.0/conf/create-replace-delete" in conf
        spec = c.get("/openapi.json").json()
        assert "/collections/{mapId}/items/{featureId}" in spec["paths"]
        assert {"get", "put", "patch", "delete"} <= set(spec["paths"]["/collections/{mapId}/items/{featureId}"])


def test_create_list_and_delete_collections(api):
    map_id = api.new_map()
    with api.client() as c:
        ids = [col["id"] for col in c.get("/collections").json()["collections"]]
        assert map_id in ids
        col = c.get(f"/collections/{map_id}").json()
        assert col["storageCrs"] == "http://www.opengis.net/def/crs/EPSG/0/25832"
        assert any(link["rel"] == "items" for link in col["links"])
        assert_problem(c.post("/collections", json={"id": map_id}, headers=api.auth), 409, map_id)
        assert_problem(c.post("/collections", json={"id": "bad id!"}, headers=api.auth), 422, "body id")
        assert_problem(c.post("/collections", json={"id": "m", "crs": "EPSG:4326"}, headers=api.auth), 400, "metric")
        assert_problem(c.post("/collections", json={"id": 5}, headers=api.auth), 422, "body id")
        assert c.delete(f"/collections/{map_id}", headers=api.auth).status_code == 204
        assert_problem(c.get(f"/collections/{map_id}"), 404, map_id)
        assert_problem(c.delete(f"/collections/{map_id}", headers=api.auth), 404)


def test_a_map_is_retitled_and_nothing_else_changes(api):
    map_id = api.new_map()
    with api.client() as c:
        before = c.get(f"/collections/{map_id}").json()
        r = c.patch(f"/collections/{map_id}", json={"title": "Durlacher Tor, surveyed 2026"}, headers=api.auth)
        assert r.status_code == 200, r.text
        after = c.get(f"/collections/{map_id}").json()
        assert after["title"] == r.json()["title"] == "Durlacher Tor, surveyed 2026"
        assert {k: v for k, v in after.items() if k != "title"} == {k: v for k, v in before.items() if k != "title"}
        assert_problem(c.patch(f"/collections/{map_id}", json={"title": "x"}), 401)
        assert_problem(c.patch(f"/collections/{map_id}", json={"title": "x", "crs": "EPSG:25833"},
                               headers=api.auth), 422, "crs")  # fmt: skip
        assert_problem(c.patch(f"/collections/{map_id}", json={"title": "x" * 501}, headers=api.auth), 422)
        assert_problem(c.patch("/collections/no-such-map", json={"title": "x"}, headers=api.auth), 404)
        assert c.get(f"/collections/{map_id}").json()["title"] == "Durlacher Tor, surveyed 2026"


def test_import_then_page_through_all_items(api, imported, karlsruhe_fc):
    map_id, result = imported
    n = len(karlsruhe_fc["features"])
    assert result["imported"] == n
    with api.client() as c:
        col = c.get(f"/collections/{map_id}").json()
        w, s, e, nn = col["extent"]["spatial"]["bbox"][0]
        assert 8.3 < w < e < 8.5 and 48.9 < s < nn < 49.1  # Karlsruhe
        seen = []
        url = f"/collections/{map_id}/items?limit=300"
        pages = 0
        while url:
            r = c.get(url)
            assert r.status_code == 200 and r.headers["content-type"].startswith("application/geo+json")
            page = r.json()
            assert page["numberMatched"] == n
            assert page["numberReturned"] == len(page["features"]) <= 300
            seen += [f["id"] for f in page["features"]]
            nxt = [link["href"] for link in page["links"] if link["rel"] == "next"]
            url = nxt[0] if nxt else None
            pages += 1
        assert pages == math.ceil(n / 300)
        assert len(seen) == len(set(seen)) == n
        last = c.get(f"/collections/{map_id}/items?limit=300&offset=300").json()
        assert any(link["rel"] == "prev" for link in last["links"])


def test_a_maps_summary_counts_its_markings_and_its_review(api):
    """``GET /collections/{id}/summary``: the counts equal the items', the review follows a
    changeset, and the map links to it."""
    map_id = api.new_map(prefix="sum")
    feats = [feature(8.428 + k * 1e-4, 49.0071, source="detected", score=k / 10, kind="dash" if k < 3 else None)
             for k in range(10)]  # fmt: skip
    feats += [feature(8.428 + k * 1e-4, 49.0072, source="manual", status="accepted") for k in range(2)]
    with api.client(headers=api.auth) as c:
        assert c.post(f"/collections/{map_id}/import", json={"type": "FeatureCollection", "features": feats}).status_code == 201
        items = c.get(f"/collections/{map_id}/items", params={"limit": 100}).json()["features"]
        low = min((f for f in items if f["properties"]["source"] == "detected"), key=lambda f: f["properties"]["score"])
        assert c.post(f"/collections/{map_id}/changesets", json={"changes": [
            {"op": "update", "id": low["id"], "patch": {"properties": {"status": "rejected"}}}]}).status_code == 201
        href = [ln["href"] for ln in c.get(f"/collections/{map_id}").json()["links"] if ln["rel"] == "summary"]
        assert len(href) == 1
        r = c.get(href[0])
        assert r.status_code == 200 and r.headers["x-map-revision"] == str(r.json()["revision"])
        sm = r.json()
    assert sm["numberOfFeatures"] == 12 and sm["byStatus"] == {"accepted": 2, "rejected": 1, "unreviewed": 9}
    assert sm["bySource"] == {"detected": 10, "manual": 2} and sm["byKind"] == {"dash": 3, "unknown": 9}
    assert sm["review"]["detections"] == {"unreviewed": 9, "accepted": 0, "rejected": 1}
    assert sm["review"]["reviewedShare"] == pytest.approx(0.1)
    bins = sm["review"]["unreviewedScores"]
    assert [b["count"] for b in bins] == [0] + [1] * 9 and (bins[0]["min"], bins[-1]["max"]) == (0.0, 1.0)
    with api.client() as c:
        assert_problem(c.get("/collections/no-such-map/summary"), 404)
        # a district: the first three detections only (scores 0, 0.1 and 0.2; the first rejected)
        part = c.get(f"/collections/{map_id}/summary", params={"bbox": "8.42795,49.007,8.42825,49.00715"}).json()
        assert part["numberOfFeatures"] == 3 and part["review"]["detections"] == {"unreviewed": 2, "accepted": 0,
                                                                                  "rejected": 1}  # fmt: skip
        assert [b["count"] for b in part["review"]["unreviewedScores"]][:3] == [0, 1, 1]
        away = c.get(f"/collections/{map_id}/summary", params={"bbox": "1,1,2,2"}).json()
        assert away["numberOfFeatures"] == 0 and away["review"]["reviewedShare"] is None
        assert_problem(c.get(f"/collections/{map_id}/summary", params={"bbox": "1,2,3"}), 400, "bbox")


def test_bbox_returns_exactly_the_features_inside(api, imported):
    map_id, _ = imported
    with api.client() as c:
        everything = c.get(f"/collections/{map_id}/items?limit=10000").json()["features"]
        lons = sorted(f["geometry"]["coordinates"][0] for f in everything)
        lats = sorted(f["geometry"]["coordinates"][1] for f in everything)
        box = (lons[len(lons) // 4], lats[len(lats) // 4], lons[len(lons) // 2], lats[3 * len(lats) // 4])
        r = c.get(f"/collections/{map_id}/items", params={"bbox": ",".join(map(str, box)), "limit": 10000})
        got = {f["id"] for f in r.json()["features"]}
        eps = 1e-7  # ~1 cm: the box is converted to the storage CRS
        inside = {f["id"] for f in everything
                  if box[0] + eps <= f["geometry"]["coordinates"][0] <= box[2] - eps
                  and box[1] + eps <= f["geometry"]["coordinates"][1] <= box[3] - eps}  # fmt: skip
        near = {f["id"] for f in everything
                if box[0] - eps <= f["geometry"]["coordinates"][0] <= box[2] + eps
                and box[1] - eps <= f["geometry"]["coordinates"][1] <= box[3] + eps}  # fmt: skip
        assert inside and inside <= got <= near
        assert r.json()["numberMatched"] == len(got)
        far = c.get(f"/collections/{map_id}/items", params={"bbox": "-10,-10,-9,-9"}).json()
        assert far["numberMatched"] == 0 and far["features"] == []
        world = c.get(f"/collections/{map_id}/items", params={"bbox": "-180,-90,180,90", "limit": 1}).json()
        assert world["numberMatched"] == len(everything)


@pytest.mark.parametrize("bbox", ["1,2,3", "a,b,c,d", "0,0,nan,1", "0,0,inf,1", "0,10,1,5", "10,0,5,1",
                                  "-200,0,0,1", "0,-95,1,0", "1e999,0,1,1"])  # fmt: skip
def test_bad_bbox_is_400(api, imported, bbox):
    map_id, _ = imported
    r = httpx.get(f"{api.base_url}/collections/{map_id}/items", params={"bbox": bbox})
    assert_problem(r, 400, "bbox")


def test_limits_and_offsets(api, imported):
    map_id, _ = imported
    with api.client() as c:
        assert_problem(c.get(f"/collections/{map_id}/items?limit=0"), 422, "limit")
        assert_problem(c.get(f"/collections/{map_id}/items?offset=-1"), 422, "offset")
        assert_problem(c.get(f"/collections/{map_id}/items?limit=abc"), 422, "limit")
        big = c.get(f"/collections/{map_id}/items?limit=99999999999").json()
        assert big["numberReturned"] == big["numberMatched"]
        default = c.get(f"/collections/{map_id}/items").json()
        assert default["numberReturned"] == 100
        beyond = c.get(f"/collections/{map_id}/items?offset=100000").json()
        assert beyond["numberReturned"] == 0 and beyond["numberMatched"] > 0
        assert_problem(c.get(f"/collections/{map_id}/items?status=maybe"), 400, "status")


def test_create_read_replace_patch_delete_with_etags(api):
    map_id = api.new_map()
    base = f"/collections/{map_id}/items"
    with api.client(headers=api.auth) as c:
        r = c.post(base, json=feature(8.428, 49.0071, weight=140, kind="dash", score=0.9))
        assert r.status_code == 201, r.text
        fid = r.json()["id"]
        assert r.headers["location"].endswith(f"{base}/{fid}")
        assert r.headers["etag"] == '"1"'
        assert r.json()["properties"]["source"] == "manual"
        g = c.get(f"{base}/{fid}")
        assert g.headers["etag"] == '"1"'
        h = c.head(f"{base}/{fid}")
        assert h.status_code == 200 and h.headers["etag"] == '"1"' and h.content == b""
        assert g.json()["geometry"]["coordinates"] == pytest.approx([8.428, 49.0071], abs=1e-9)
        # PUT replaces, If-Match honoured
        put = c.put(f"{base}/{fid}", json=feature(8.4281, 49.0072, weight=50, status="accepted"),
                    headers={"If-Match": '"1"'})  # fmt: skip
        assert put.status_code == 200, put.text
        assert put.headers["etag"] == '"2"'
        assert put.json()["properties"]["weight"] == 50 and put.json()["properties"]["status"] == "accepted"
        assert put.json()["geometry"]["coordinates"] == pytest.approx([8.4281, 49.0072], abs=1e-9)
        stale = c.put(f"{base}/{fid}", json=feature(8.0, 49.0), headers={"If-Match": '"1"'})
        assert_problem(stale, 412, "version 2")
        assert c.get(f"{base}/{fid}").json()["properties"]["weight"] == 50
        # PATCH without If-Match (as QGIS does), merge-patch null removes the score
        p = c.patch(f"{base}/{fid}", content=b'{"properties": {"score": null, "status": "rejected"}}',
                    headers={"Content-Type": "application/merge-patch+json"})  # fmt: skip
        assert p.status_code == 200, p.text
        props = p.json()["properties"]
        assert props["score"] is None and props["status"] == "rejected" and props["weight"] == 50
        assert p.headers["etag"] == '"3"'
        # a patch that changes nothing keeps the version, and the position does not drift
        same = c.patch(f"{base}/{fid}", json={"properties": {"status": "rejected"}})
        assert same.headers["etag"] == '"3"'
        assert same.json()["geometry"]["coordinates"] == put.json()["geometry"]["coordinates"]
        assert_problem(c.patch(f"{base}/{fid}", json={"properties": {"weight": -1}}), 422, "weight")
        assert_problem(c.patch(f"{base}/{fid}", json={"geometry": None}), 422, "geometry")
        assert_problem(c.delete(f"{base}/{fid}", headers={"If-Match": '"2"'}), 412)
        assert c.delete(f"{base}/{fid}", headers={"If-Match": '"3"'}).status_code == 204
        assert_problem(c.get(f"{base}/{fid}"), 404, fid)
        assert_problem(c.patch(f"{base}/{fid}", json={"properties": {"status": "accepted"}}), 404)
        assert_problem(c.delete(f"{base}/{fid}"), 404)


def test_qgis_style_create_with_null_attributes(api):
    """QGIS posts every attribute of the layer, null where the user left it empty."""
    map_id = api.new_map()
    body = feature(8.428, 49.0071, weight=None, length_m=None, width_m=None, bearing_deg=None, score=None,
                   kind=None, source=None, status=None, version=None)  # fmt: skip
    body["id"] = None
    with api.client(headers={**api.auth, "Content-Type": "application/geo+json"}) as c:
        r = c.post(f"/collections/{map_id}/items", json=body)
        assert r.status_code == 201, r.text
        props = r.json()["properties"]
        assert props["source"] == "manual" and props["status"] == "unreviewed" and props["weight"] == 1.0
        fid = r.json()["id"]
        put = c.put(f"/collections/{map_id}/items/{fid}", json={**body, "properties": {**body["properties"],
                    "status": "accepted"}})  # fmt: skip
        assert put.status_code == 200 and put.json()["properties"]["status"] == "accepted"
        assert put.json()["properties"]["source"] == "manual"


def test_options_answers_allow(api):
    map_id = api.new_map()
    with api.client(headers=api.auth) as c:
        fid = c.post(f"/collections/{map_id}/items", json=feature(8.428, 49.0071)).json()["id"]
        r = c.options(f"/collections/{map_id}/items")
        assert {"GET", "POST"} <= {m.strip() for m in r.headers["allow"].split(",")}
        r = c.options(f"/collections/{map_id}/items/{fid}")
        assert {"GET", "PUT", "PATCH", "DELETE"} <= {m.strip() for m in r.headers["allow"].split(",")}


@pytest.mark.parametrize("body", [
    {"type": "Feature", "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 1]]}, "properties": {}},
    {"type": "Feature", "geometry": {"type": "Point", "coordinates": [200, 0]}, "properties": {}},
    {"type": "Feature", "geometry": {"type": "Point", "coordinates": ["a", 0]}, "properties": {}},
    {"type": "Feature", "geometry": {"type": "Point", "coordinates": [8.4, 49.0]}, "properties": {"status": "x"}},
    {"type": "Feature", "geometry": {"type": "Point", "coordinates": [8.4, 49.0]}, "properties": {"weight": "1"}},
    {"type": "Feature", "properties": {}},
    [1, 2, 3],
    "Feature",
])  # fmt: skip
def test_invalid_features_are_422_and_write_nothing(api, body):
    map_id = api.new_map()
    with api.client(headers=api.auth) as c:
        r = c.post(f"/collections/{map_id}/items", json=body)
        assert_problem(r, 422)
        assert c.get(f"/collections/{map_id}/items").json()["numberMatched"] == 0


def test_writes_need_a_valid_token(api):
    map_id = api.new_map()
    with api.client() as c:
        r = c.post(f"/collections/{map_id}/items", json=feature(8.428, 49.0071))
        assert_problem(r, 401, "Bearer")
        assert r.headers["www-authenticate"].startswith("Bearer")
        r = c.post(f"/collections/{map_id}/items", json=feature(8.428, 49.0071),
                   headers={"Authorization": "Bearer wrong"})  # fmt: skip
        assert_problem(r, 401, "not valid")
        assert_problem(c.delete(f"/collections/{map_id}"), 401)
        assert c.get(f"/collections/{map_id}/items").json()["numberMatched"] == 0
        assert c.get(f"/collections/{map_id}").status_code == 200


def test_import_errors_name_the_feature(api):
    map_id = api.new_map()
    fc = {"type": "FeatureCollection", "features": [feature(8.4, 49.0), feature(8.4, 95.0)]}
    with api.client(headers=api.auth) as c:
        assert_problem(c.post(f"/collections/{map_id}/import", json=fc), 422, "feature 1")
        assert_problem(c.post(f"/collections/{map_id}/import", json={"type": "Nope"}), 422, "FeatureCollection")
        assert c.get(f"/collections/{map_id}/items").json()["numberMatched"] == 0


def test_an_import_reads_its_own_body_and_writes_all_of_it_or_nothing(api):
    """An import reads its body itself (it may be larger than other JSON bodies): what is not
    JSON is 400, JSON that is not markings 422, an unknown map 404, and a body whose last
    marking is bad writes none of the thousands before it."""
    map_id = api.new_map()
    json_type = {**api.auth, "Content-Type": "application/geo+json"}
    with api.client(headers=json_type) as c:
        for body, status, words in (
            (b'{"type": "FeatureCollection", "features": [', 400, ("not valid JSON",)),
            (b'{"type": "FeatureCollection", "features": [NaN]}', 400, ("NaN",)),
            (b'{"type": "FeatureCollection", "features": [], "x": 1e999}', 400, ("1e999",)),
            (b"[" * 100_000 + b"]" * 100_000, 400, ("nested too deeply",)),
            ('{"type": "FeatureCollection"}'.encode("utf-16"), 400, ("UTF-8",)),
            (b"", 422, ("empty",)),
            (b'{"type": "FeatureCollection", "features": []}', 422, ("no features",)),
            (b'{"type": "Feature"}', 422, ("Point",)),
        ):  # fmt: skip
            assert_problem(c.post(f"/collections/{map_id}/import", content=body), status, *words)
        ok = b'{"type": "FeatureCollection", "features": [{"type": "Feature", "geometry": {"type": "Point", ' \
             b'"coordinates": [8.4, 49.0]}, "properties": {}}]}'
        assert_problem(c.post("/collections/no-such-map/import", content=ok), 404)
        feats = [feature(8.4 + 1e-6 * k, 49.0) for k in range(12_000)]
        feats[-1]["properties"]["weight"] = -1
        r = c.post(f"/collections/{map_id}/import", json={"type": "FeatureCollection", "features": feats})
        assert_problem(r, 422, "feature 11999", "weight")
        assert c.get(f"/collections/{map_id}/items").json()["numberMatched"] == 0
        feats[-1]["properties"]["weight"] = 2.0
        r = c.post(f"/collections/{map_id}/import", json={"type": "FeatureCollection", "features": feats},
                   params={"comment": "a district"})  # fmt: skip
        assert r.status_code == 201 and r.json()["imported"] == 12_000
        assert c.get(f"/collections/{map_id}/items").json()["numberMatched"] == 12_000
        assert c.get(f"/collections/{map_id}/changesets").json()["changesets"][0]["comment"] == "a district"
    assert not list((api.data_dir / "imports").glob("*"))  # read from the data folder, and gone


def _finished(c: httpx.Client, url: str, timeout: float = 120) -> dict:
    deadline = time.monotonic() + timeout
    seen = []
    while time.monotonic() < deadline:
        job = c.get(url).json()
        seen.append((job["status"], job["progress"]))
        if job["status"] in ("successful", "failed", "dismissed"):
            return {**job, "seen": seen}
        time.sleep(0.05)
    raise AssertionError(f"{url} did not finish: {seen[-5:]}")


def _gone(folder, timeout: float = 10) -> None:
    """Wait for ``folder`` to hold no file: a job's body is removed as its process ends."""
    deadline = time.monotonic() + timeout
    while list(folder.glob("*")) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not list(folder.glob("*"))


def test_an_import_preferred_async_is_a_job_that_writes_all_of_it_or_nothing(api):
    """``Prefer: respond-async``: 202 at once with the job (``Location``), whose progress moves
    while it runs, which answers what the import wrote, and whose body is not kept once it
    ended. A bad body fails the job with the error the import would answer, writing nothing."""
    map_id = api.new_map()
    prefer = {**api.auth, "Content-Type": "application/geo+json", "Prefer": "wait=5, respond-async"}
    imports = api.data_dir / "imports"
    feats = [feature(8.4 + 1e-6 * k, 49.0 + 1e-6 * (k % 7)) for k in range(40_000)]
    with api.client(headers=prefer) as c:
        r = c.post(f"/collections/{map_id}/import", json={"type": "FeatureCollection", "features": feats},
                   params={"comment": "a district"})  # fmt: skip
        assert r.status_code == 202, r.text
        assert r.headers["preference-applied"] == "respond-async"
        assert r.json()["processID"] == "import" and r.json()["status"] in ("accepted", "running")
        job = _finished(c, r.headers["location"])
        assert job["status"] == "successful", job
        assert job["progress"] == 100 and [p for st, p in job["seen"] if 0 < p < 100], job["seen"]
        got = job["result"]
        assert got["imported"] == 40_000 and int(got["last_id"]) - int(got["first_id"]) == 39_999
        assert c.get(f"/collections/{map_id}/items").json()["numberMatched"] == 40_000
        cs = c.get(next(x["href"] for x in job["links"] if x["rel"] == "changeset")).json()
        assert cs["comment"] == "a district" and cs["id"] == got["changeset"]
        _gone(imports)

        feats[-1]["properties"]["weight"] = -1
        for body, words in ((json.dumps({"type": "FeatureCollection", "features": feats}).encode(),
                             ("feature 39999", "weight")),
                            (b'{"type": "FeatureCollection", "features": [', ("not valid JSON",)),
                            (b'{"type": "FeatureCollection", "features": []}', ("no features",))):  # fmt: skip
            r = c.post(f"/collections/{map_id}/import", content=body)
            assert r.status_code == 202, r.text
            job = _finished(c, r.headers["location"])
            assert job["status"] == "failed" and all(w in job["message"] for w in words), job
            assert "result" not in job and str(imports) not in job["message"]
        assert c.get(f"/collections/{map_id}/items").json()["numberMatched"] == 40_000
        _gone(imports)
        # Cancelled (DELETE /jobs/{id}) while it reads or writes: dismissed, nothing written, no body kept.
        big = [feature(8.41 + 1e-6 * k, 49.01) for k in range(150_000)]
        r = c.post(f"/collections/{map_id}/import", json={"type": "FeatureCollection", "features": big})
        assert r.status_code == 202, r.text
        assert c.delete(r.headers["location"]).status_code == 200
        job = _finished(c, r.headers["location"])
        assert job["status"] == "dismissed" and "result" not in job, job
        time.sleep(1.0)  # a process ended mid-write has rolled back; one that was not would commit now
        assert c.get(f"/collections/{map_id}/items").json()["numberMatched"] == 40_000
        _gone(imports)
        # Refused before it is a job: what the synchronous import refuses at once.
        assert_problem(c.post(f"/collections/{map_id}/import", content=b""), 422, "empty")
        assert_problem(c.post("/collections/no-such-map/import", content=b"{}"), 404)
        assert_problem(c.post(f"/collections/{map_id}/import", content=b"{}",
                              headers={"Content-Type": "text/plain"}), 415)  # fmt: skip
