"""The web map editor, end to end: Debian's Chromium (headless, through Playwright) against a
real ``lanemap serve``, checked through the HTTP API.

One server and one browser serve the whole module; each test gets a map of its
own (same markings and imagery) and a fresh browser context (empty storage).
"""

from __future__ import annotations

import json
import math
import uuid

import httpx
import pytest
from PIL import Image
from playwright.sync_api import sync_playwright

from tests._api_helpers import feature, start_server
from tests._editor_helpers import ARTIFACTS, create_map, launch, metres_between, render_window


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("editor")
    srv = start_server(f"sqlite:///{tmp / 'lanemap.sqlite'}", tmp / "data")
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def window(tmp_path_factory):
    return render_window(tmp_path_factory.mktemp("window"))


@pytest.fixture(scope="module")
def browser():
    with sync_playwright() as p:
        b = launch(p)
        yield b
        b.close()


@pytest.fixture
def fx(server, window):
    return create_map(server, window, f"ka-{uuid.uuid4().hex[:8]}")


class Editor:
    """The editor page of one map, with what the tests do in it."""

    def __init__(self, browser, server, fx):
        self.server, self.fx = server, fx
        self.context = browser.new_context(viewport={"width": 1280, "height": 800})
        self.errors: list[str] = []
        self.responses: list[tuple[int, str]] = []
        self.page = self.new_page()

    def new_page(self):
        page = self.context.new_page()
        page.on("pageerror", lambda e: self.errors.append(str(e)))
        page.on("response", lambda r: self.responses.append((r.status, r.url)))
        return page

    def open(self, page=None):
        self.page = page or self.page
        self.page.goto(f"{self.server.base_url}/editor/#map={self.fx.map_id}")
        self.wait_loaded()
        return self

    def wait_loaded(self):
        self.page.wait_for_selector("body[data-loaded]")
        self.page.wait_for_function("lanemapEditor.layer.size > 0")

    def enter_token(self, token=None):
        self.page.fill("#token-input", token or self.server.token)
        self.page.click("#token-use")
        self.page.wait_for_selector("#readonly", state="hidden")

    def px(self, lon, lat):
        """Page pixel of a lon/lat (whole pixels, as the browser's mouse events have them)."""
        return self.page.evaluate(
            """([lon, lat]) => {
                 const m = lanemapEditor.map, p = m.latLngToContainerPoint([lat, lon]);
                 const r = m.getContainer().getBoundingClientRect();
                 return [Math.round(r.left + p.x), Math.round(r.top + p.y)];
               }""",
            [lon, lat],
        )

    def lonlat(self, x, y):
        """Lon/lat under a page pixel, as Leaflet reads it from a mouse event there."""
        return self.page.evaluate(
            """([x, y]) => {
                 const ll = lanemapEditor.map.mouseEventToLatLng({clientX: x, clientY: y});
                 return [ll.lng, ll.lat];
               }""",
            [x, y],
        )

    def click_marking(self, fid, shift=False):
        if shift:
            self.page.keyboard.down("Shift")
        self.page.mouse.click(*self.px(*self.fx.lonlat(fid)))
        if shift:
            self.page.keyboard.up("Shift")

    def drag(self, a, b, steps=8):
        m = self.page.mouse
        m.move(*a)
        m.down()
        m.move(*b, steps=steps)
        m.up()

    def unsaved(self) -> int:
        return int(self.page.text_content("#unsaved").split()[0])

    def pending(self) -> dict:
        return self.page.evaluate("Object.fromEntries(lanemapEditor.state.session.pending)")

    def selection(self) -> set[str]:
        return set(self.page.evaluate("[...lanemapEditor.state.selection]"))

    def key(self, key):
        self.page.keyboard.press(key)

    def save(self, comment):
        self.page.click("#save")
        self.page.fill("#save-comment", comment)
        self.page.click("#save-confirm")

    def close(self):
        self.context.close()
        assert not self.errors, self.errors
        assert not [r for r in self.responses if r[0] >= 500], self.responses


@pytest.fixture
def editor(browser, server, fx):
    ed = Editor(browser, server, fx)
    yield ed
    ed.close()


def api_get(server, path, **params):
    r = httpx.get(f"{server.base_url}{path}", params=params, timeout=30)
    assert r.status_code == 200, r.text
    return r.json()


# ---------------------------------------------------------------------------------------------


def test_page_shows_imagery_and_markings_and_is_read_only_without_a_token(editor, fx, tmp_path):
    editor.open()
    page = editor.page
    editor.page.wait_for_load_state("networkidle")
    # The basemap: the map's imagery tiles came from the tile endpoint as PNGs.
    tiles = [(s, u) for s, u in editor.responses if "/imagery/tiles/WebMercatorQuad/" in u]
    assert sum(s == 200 for s, _ in tiles) >= 4, tiles
    assert all(s in (200, 404) for s, _ in tiles)  # 404: outside the imagery
    assert page.evaluate("document.querySelectorAll('.leaflet-tile-loaded').length") >= 4
    # Every marking is drawn.
    assert page.evaluate("lanemapEditor.layer.size") == len(fx.features)

    # Drawn where they are, coloured by source: an accepted imported marking's centroid pixel is cyan.
    shot = tmp_path / "page.png"
    page.screenshot(path=str(shot))
    img = Image.open(shot).convert("RGB")
    cyan = fx.isolated(source="imported", status="accepted")[0]
    x, y = editor.px(*fx.lonlat(cyan))
    r, g, b = img.getpixel((round(x), round(y)))
    assert b > 180 and g > 150 and r < 140, (r, g, b)

    # Read-only: it says so, editing tools are off, and keys change nothing.
    assert page.is_visible("#readonly")
    assert "Read-only" in page.text_content("#readonly")
    assert page.is_disabled("#mode-add")
    target = fx.isolated(source="detected")[0]
    editor.click_marking(target)
    assert editor.selection() == {target}
    editor.key("r")
    editor.key("Delete")
    assert editor.unsaved() == 0
    assert "Read-only" in page.text_content("#toast")

    # A token the server refuses is not taken.
    page.fill("#token-input", "not-the-token")
    page.click("#token-use")
    page.wait_for_function("document.getElementById('toast').textContent.includes('does not accept')")
    assert page.is_visible("#readonly")
    assert page.evaluate("sessionStorage.getItem('lanemap.token')") is None
    # The right one is, once for the browser session.
    editor.enter_token()
    assert page.evaluate("sessionStorage.getItem('lanemap.token')") == editor.server.token
    assert page.is_enabled("#mode-add")


def test_edits_are_saved_as_one_changeset(editor, fx, server):
    editor.open().enter_token()
    page = editor.page
    before = api_get(server, f"/collections/{fx.map_id}/changesets")["numberMatched"]

    # Reject a detection.
    rejected = fx.isolated(source="detected")[0]
    editor.click_marking(rejected)
    editor.key("r")
    assert editor.unsaved() == 1

    # Add one by drawing its two ends.
    lon0, lat0 = fx.lonlat(fx.isolated(8.0)[0])
    x0, y0 = editor.px(lon0, lat0)
    a, b = (x0 + 60, y0 + 50), (x0 + 90, y0 + 70)
    end_a, end_b = editor.lonlat(*a), editor.lonlat(*b)
    editor.key("n")
    editor.drag(a, b)
    editor.key("v")
    assert editor.unsaved() == 2

    # Move one by dragging it.
    moved = fx.isolated(source="imported")[1]
    start = editor.px(*fx.lonlat(moved))
    stop = (start[0] + 40, start[1] + 25)
    d_lon = editor.lonlat(*stop)[0] - editor.lonlat(*start)[0]
    d_lat = editor.lonlat(*stop)[1] - editor.lonlat(*start)[1]
    editor.drag(start, stop)
    assert editor.unsaved() == 3

    # Delete one, then undo that; redo and undo again.
    deleted = fx.isolated(source="manual")[0]
    editor.click_marking(deleted)
    editor.key("Delete")
    assert editor.unsaved() == 4
    editor.key("Control+z")
    assert editor.unsaved() == 3
    editor.key("Control+Shift+z")
    assert editor.unsaved() == 4
    editor.key("Control+z")
    assert editor.unsaved() == 3
    assert page.text_content("#unsaved") == "3 unsaved"

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "editor-unsaved.png"))
    editor.save("editor test: reject, add, move")
    page.wait_for_function("document.getElementById('unsaved').textContent === '0 unsaved'")
    assert "Saved changeset" in page.text_content("#toast")
    assert page.evaluate("localStorage.length") == 0

    # The API's history holds exactly those three changes, in one changeset.
    cs_list = api_get(server, f"/collections/{fx.map_id}/changesets")
    assert cs_list["numberMatched"] == before + 1
    cs = cs_list["changesets"][0]
    assert (cs["comment"], cs["who"]) == ("editor test: reject, add, move", "api")
    assert (cs["created"], cs["updated"], cs["deleted"]) == (1, 2, 0)
    edits = api_get(server, f"/collections/{fx.map_id}/changesets/{cs['id']}")["edits"]
    by_op = {}
    for e in edits:
        by_op.setdefault(e["op"], []).append(e)
    assert sorted(by_op) == ["create", "update"] and len(edits) == 3
    updates = {e["feature_id"]: e for e in by_op["update"]}
    assert set(updates) == {rejected, moved}
    status = updates[rejected]["before"]["status"], updates[rejected]["after"]["status"]
    assert status == ("unreviewed", "rejected")

    r = httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{rejected}").json()
    assert r["properties"]["status"] == "rejected"
    assert r["geometry"]["coordinates"] == fx.features[rejected]["geometry"]["coordinates"]

    # Positions within a centimetre (the server keeps them in its metric CRS).
    m = httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{moved}").json()
    lon, lat = fx.lonlat(moved)
    assert m["geometry"]["coordinates"][0] == pytest.approx(lon + d_lon, abs=1e-7)
    assert m["geometry"]["coordinates"][1] == pytest.approx(lat + d_lat, abs=1e-7)
    for k in ("length_m", "bearing_deg", "status", "source"):
        assert m["properties"][k] == pytest.approx(fx.features[moved]["properties"][k])

    new_id = by_op["create"][0]["feature_id"]
    n = httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{new_id}").json()
    (nlon, nlat), p = n["geometry"]["coordinates"], n["properties"]
    assert nlon == pytest.approx((end_a[0] + end_b[0]) / 2, abs=1e-7)
    assert nlat == pytest.approx((end_a[1] + end_b[1]) / 2, abs=1e-7)
    assert p["length_m"] == pytest.approx(metres_between(*end_a, *end_b), rel=1e-3)
    de = math.radians(end_b[0] - end_a[0]) * 6378137 * math.cos(math.radians(nlat))
    dn = math.radians(end_b[1] - end_a[1]) * 6378137
    assert p["bearing_deg"] == pytest.approx(math.degrees(math.atan2(de, dn)) % 180, abs=0.05)
    assert (p["source"], p["status"]) == ("manual", "accepted")

    # The undone delete never reached the server.
    assert httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{deleted}").status_code == 200

    # The history panel lists the new changeset; the screenshot shows the map after the save.
    page.wait_for_selector(f"#history-list li[data-changeset='{cs['id']}']")
    item = page.text_content(f"#history-list li[data-changeset='{cs['id']}']")
    assert "editor test: reject, add, move" in item and "api" in item
    # The screenshot (docs/editor.png is one): closer in, a doubtful detection selected.
    middle = [sum(c) / len(fx.features) for c in zip(*(fx.lonlat(f) for f in fx.features))]
    doubtful = [f for f in fx.isolated(3.0, source="detected") if fx.features[f]["properties"]["score"] < 0.5]
    low = min(doubtful, key=lambda f: metres_between(*fx.lonlat(f), *middle))
    page.evaluate(
        """([lon, lat]) => new Promise((done) => {
             const m = lanemapEditor.map;
             m.eachLayer((l) => { if (l instanceof L.TileLayer) l.once('load', () => done(true)); });
             m.setView([lat, lon], 20, {animate: false});
           })""",
        middle,
    )
    editor.click_marking(low)
    page.evaluate("document.getElementById('toast').className = ''")
    page.wait_for_timeout(300)  # the toast fades out
    page.screenshot(path=str(ARTIFACTS / "editor.png"))


def test_the_page_doubts_lengths_by_the_localizers_own_numbers():
    """The page repeats the localizer's rule in JavaScript: its numbers must be the index's."""
    import re
    from pathlib import Path

    from localizer import index

    js = (Path(__file__).resolve().parents[1] / "service" / "static" / "editor" / "layer.js").read_text()
    rule = re.search(r"LENGTH_DOUBT = \{([^}]*)\}", js).group(1)
    got = {k.strip(): float(v) for k, v in (kv.split(":") for kv in rule.split(","))}
    assert got == {"cellM": index.TYPICAL_CELL_M, "minCount": index.TYPICAL_MIN,
                   "tolerance": index.LENGTH_TOLERANCE, "maxLengthM": index.MAX_DASH_LENGTH_M}


def test_detections_whose_length_the_localizer_doubts_stand_out_and_are_explained(editor, fx, server):
    """Eight detections of unknown kind in one 40 m square of the page's grid: six 3 m dashes,
    a 1.2 m piece (a dash half hidden) and a 5.5 m one (run into something). The odd two
    are doubted, the dashes not; the review queue says why; once a kind is set, it is not."""
    r0 = 6378137.0
    middle = [sum(c) / len(fx.features) for c in zip(*(fx.lonlat(f) for f in fx.features))]
    k = math.cos(math.radians(math.floor(middle[1])))
    # The middle of the page grid's square that holds the window's middle.
    east = (math.floor(math.radians(middle[0]) * r0 * k / 40.0) + 0.5) * 40.0
    north = (math.floor(math.radians(middle[1]) * r0 / 40.0) + 0.5) * 40.0
    lon0, lat0 = math.degrees(east / (r0 * k)), math.degrees(north / r0)

    def at(de, dn):
        return [lon0 + math.degrees(de / (r0 * math.cos(math.radians(lat0)))), lat0 + math.degrees(dn / r0)]

    marks = [(at(-12.0 + 4.0 * i, 1.5 * (i % 2)), 3.0, 0.5 + 0.01 * i) for i in range(6)]
    marks.append((at(0.0, -4.0), 1.2, 0.011))  # the review queue's first
    marks.append((at(8.0, -4.0), 5.5, 0.7))  # run into something
    feats = [{"type": "Feature", "geometry": {"type": "Point", "coordinates": c},
              "properties": {"length_m": length, "width_m": 0.12, "bearing_deg": 90.0, "weight": 30.0,
                             "score": score, "source": "detected", "status": "unreviewed"}}
             for c, length, score in marks]  # fmt: skip
    with server.client(headers=server.auth) as c:
        assert c.post(f"/collections/{fx.map_id}/import", json={"type": "FeatureCollection", "features": feats},
                      params={"comment": "detections of unknown kind"}).status_code == 201  # fmt: skip
        got = c.get(f"/collections/{fx.map_id}/items", params={"limit": 10000}).json()["features"]
    ids = {f["properties"]["score"]: f["id"] for f in got if f["properties"].get("kind") is None
           and f["properties"]["source"] == "detected"}  # fmt: skip
    short, long_, dashes = ids[0.011], ids[0.7], [ids[round(0.5 + 0.01 * i, 3)] for i in range(6)]

    editor.open().enter_token()
    page = editor.page
    page.evaluate("([lon, lat]) => { lanemapEditor.map.setView([lat, lon], 19, {animate: false}); }", [lon0, lat0])
    page.wait_for_function(f"lanemapEditor.state.lengthDoubts.has('{short}')")
    doubts = page.evaluate("Object.fromEntries(lanemapEditor.state.lengthDoubts)")
    assert set(doubts) & set(dashes) == set()
    assert doubts[short] == pytest.approx(3.0) and doubts[long_] == pytest.approx(3.0)
    halo = page.evaluate(f"[lanemapEditor.layer.dashes.get('{long_}').halo?.options.color,"
                         f" lanemapEditor.layer.dashes.get('{short}').halo?.options.color]")
    assert halo == ["#ff8c00", "#ff2bd6"]  # a low score outranks the length
    others = page.evaluate(f"{json.dumps(dashes)}.map((id) => lanemapEditor.layer.dashes.get(id).halo?.options.color ?? null)")
    assert others == [None] * 6

    # The review queue (lowest score first) starts with it and says what is odd about it.
    page.click("#review-start")
    page.wait_for_function(f"lanemapEditor.state.selection.has('{short}')")
    status = page.text_content("#review-status")
    assert "1.20 m long where 3.00 m is typical" in status
    editor.key("Escape")

    # A person who finds it right sets its kind: the localizer then takes it as it is.
    with server.client(headers=server.auth) as c:
        r = c.patch(f"/collections/{fx.map_id}/items/{short}", json={"properties": {"kind": "dash"}},
                    headers={"If-Match": c.get(f"/collections/{fx.map_id}/items/{short}").headers["ETag"]})
        assert r.status_code == 200, r.text
    page.reload()
    editor.wait_loaded()
    page.evaluate("([lon, lat]) => { lanemapEditor.map.setView([lat, lon], 19, {animate: false}); }", [lon0, lat0])
    page.wait_for_function(f"lanemapEditor.state.lengthDoubts.has('{long_}')")
    kind = page.evaluate(f"lanemapEditor.layer.dashes.get('{short}').marking.kind")
    assert kind == "dash" and not page.evaluate(f"lanemapEditor.state.lengthDoubts.has('{short}')")


def test_a_conflicting_save_is_shown_and_loses_nothing(editor, fx, server):
    editor.open().enter_token()
    page = editor.page
    a, b = fx.isolated(source="detected")[:2]
    editor.click_marking(a)
    editor.key("r")
    start = editor.px(*fx.lonlat(b))
    editor.drag(start, (start[0] + 30, start[1]))
    c = fx.isolated(source="imported")[0]
    editor.click_marking(c)
    editor.key("Delete")
    assert editor.unsaved() == 3

    # Someone else changes marking a behind the editor's back.
    r = httpx.patch(f"{server.base_url}/collections/{fx.map_id}/items/{a}",
                    json={"properties": {"width_m": 0.3}}, headers=server.auth)  # fmt: skip
    assert r.status_code == 200
    n_before = api_get(server, f"/collections/{fx.map_id}/changesets")["numberMatched"]

    editor.save("conflicting")
    page.wait_for_selector("#conflict", state="visible")
    assert f"marking {a}" in page.text_content("#conflict-list")
    assert f"marking {b}" not in page.text_content("#conflict-list")
    assert editor.unsaved() == 3
    assert page.evaluate("[...lanemapEditor.state.conflicts.keys()]") == [a]
    stored = json.loads(page.evaluate("localStorage.getItem(Object.keys(localStorage)[0])"))
    assert {k for k, _ in stored["pending"]} == {a, b, c}
    assert api_get(server, f"/collections/{fx.map_id}/changesets")["numberMatched"] == n_before

    # Reload the conflicting marking, re-apply the edit on its new version, save.
    page.click("#conflict-rebase")
    page.wait_for_selector("#conflict", state="hidden")
    assert editor.unsaved() == 3
    assert editor.pending()[a]["base"]["version"] == "2"
    # Escape in the save dialog saves nothing (even after an earlier "Save changeset").
    page.click("#save")
    page.keyboard.press("Escape")
    page.wait_for_timeout(200)
    assert not page.evaluate("document.getElementById('save-dialog').open")
    assert api_get(server, f"/collections/{fx.map_id}/changesets")["numberMatched"] == n_before
    editor.save("after the conflict")
    page.wait_for_function("document.getElementById('unsaved').textContent === '0 unsaved'")
    got = httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{a}").json()["properties"]
    assert (got["status"], got["width_m"], got["version"]) == ("rejected", 0.3, 3)
    moved = httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{b}").json()
    assert moved["geometry"]["coordinates"] != fx.features[b]["geometry"]["coordinates"]
    assert httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{c}").status_code == 404
    cs = api_get(server, f"/collections/{fx.map_id}/changesets")["changesets"][0]
    assert (cs["comment"], cs["created"], cs["updated"], cs["deleted"]) == ("after the conflict", 0, 2, 1)


def test_what_others_save_appears_and_conflicts_show_before_saving(browser, editor, fx, server):
    """Two people on one map: what one saves appears on the other's page within a round of the
    change feed (``?live=`` ms), deletions too; an unsaved edit of a marking the other saved is
    flagged as a conflict at once, and is resolved as a refused save would be."""
    editor.page.goto(f"{server.base_url}/editor/?live=300#map={fx.map_id}")
    editor.wait_loaded()
    editor.enter_token()
    page = editor.page
    other = Editor(browser, server, fx)
    other.page.goto(f"{server.base_url}/editor/?live=300#map={fx.map_id}")
    other.wait_loaded()  # read-only: it only watches
    a, b, c = fx.isolated(source="detected")[:3]
    editor.click_marking(b)
    editor.key("a")  # an unsaved edit of b here

    # Someone else accepts a, widens b and deletes c (through the API, as QGIS would).
    body = {"comment": "elsewhere", "changes": [
        {"op": "update", "id": a, "patch": {"properties": {"status": "accepted"}}},
        {"op": "update", "id": b, "patch": {"properties": {"width_m": 0.3}}},
        {"op": "delete", "id": c}]}  # fmt: skip
    r = httpx.post(f"{server.base_url}/collections/{fx.map_id}/changesets", json=body, headers=server.auth)
    assert r.status_code == 201, r.text
    for p in (page, other.page):
        p.wait_for_function(f"lanemapEditor.state.server.get('{a}')?.status === 'accepted'", timeout=10_000)
        assert p.evaluate(f"lanemapEditor.state.server.has('{c}')") is False
        assert "changed on the server" in p.text_content("#view-status")
        p.wait_for_selector("#history-list li:has-text('elsewhere')")
        # the review's progress follows: a accepted, c (a detection) gone
        n = len(fx.detected) - 1
        p.wait_for_selector(f"#review-progress:has-text('Saved: 1 of {n} detections reviewed')")
    # here, b is a conflict before any save; the watcher has none
    page.wait_for_selector("#conflict", state="visible")
    assert "Someone else changed" in page.text_content("#conflict-title")
    assert page.evaluate("[...lanemapEditor.state.conflicts.keys()]") == [b]
    assert other.page.is_hidden("#conflict")
    assert editor.unsaved() == 1
    page.click("#conflict-rebase")
    page.wait_for_selector("#conflict", state="hidden")
    editor.save("after theirs")
    page.wait_for_function("document.getElementById('unsaved').textContent === '0 unsaved'")
    got = httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{b}").json()["properties"]
    assert (got["status"], got["width_m"]) == ("accepted", 0.3)
    # and the watcher sees this save too, while the saver's own save is not someone else's
    other.page.wait_for_function(f"lanemapEditor.state.server.get('{b}')?.status === 'accepted'", timeout=10_000)
    page.wait_for_timeout(1000)
    assert page.is_hidden("#conflict")
    other.close()


def test_a_review_by_score_elsewhere_is_taken_in_without_reading_every_change(editor, fx, server):
    """More changes at once than the page follows one by one (``lanemapEditor.follow.max``; such as a
    review by score across a city): the page reads its view again instead of every change, an unsaved
    edit of a marking changed there is a conflict all the same, and a running review goes on with
    the detections still unreviewed on the server, in score order."""
    editor.page.goto(f"{server.base_url}/editor/?live=300#map={fx.map_id}")
    editor.wait_loaded()
    editor.enter_token()
    page = editor.page
    q = fx.detected
    score = {i: fx.features[i]["properties"]["score"] for i in q}
    page.evaluate("Object.assign(lanemapEditor.follow, {max: 3}); Object.assign(lanemapEditor.reviewPaging, {page: 4, prefetch: 1})")
    page.click("#review-start")
    page.wait_for_function(f"lanemapEditor.state.selection.has('{q[0]}')")
    editor.key("a")  # an unsaved decision on the first
    page.wait_for_function(f"lanemapEditor.state.selection.has('{q[1]}')")
    # elsewhere, at once: the first is made wider and the detections from 0.5 on are accepted
    seen = len(editor.responses)
    sure = [i for i in q if score[i] >= 0.5]
    body = {"comment": "wider, and the sure ones", "changes": [
        {"op": "update", "id": q[0], "patch": {"properties": {"width_m": 0.3}}},
        *[{"op": "update", "id": i, "patch": {"properties": {"status": "accepted"}}} for i in sure]]}  # fmt: skip
    r = httpx.post(f"{server.base_url}/collections/{fx.map_id}/changesets", json=body, headers=server.auth)
    assert r.status_code == 201 and len(sure) > 3, r.text
    page.wait_for_selector("#view-status:has-text('markings changed on the server')", timeout=10_000)
    assert f"{len(sure) + 1} markings changed on the server" in page.text_content("#view-status")
    page.wait_for_selector("#conflict", state="visible")
    assert page.evaluate("[...lanemapEditor.state.conflicts.keys()]") == [q[0]]
    feeds = [u for _, u in editor.responses[seen:] if "/changes?" in u]
    assert feeds and all("limit=3" in u and "after=" not in u for u in feeds), feeds
    # the view holds what the server holds now
    shown = page.evaluate("Object.fromEntries([...lanemapEditor.state.server].map(([k, m]) => [k, m.status]))")
    assert shown and all(st == "accepted" for k, st in shown.items() if k in score and score[k] >= 0.5), shown
    page.click("#conflict-close")
    # the review goes on past the second with the detections still unreviewed there
    left = [i for i in q[2:] if score[i] < 0.5]
    assert len(left) >= 3
    for want in left[:3]:
        editor.key(" ")
        page.wait_for_function(f"lanemapEditor.state.selection.has('{want}')", timeout=10_000)


def test_a_server_error_names_the_request_to_report(editor, fx, server):
    """A 5xx on save keeps the edits and names the answer's X-Request-ID (what the server's log shows:
    tests/test_api_errors.py); the 503 is answered in the browser, as the store answers an outage."""
    editor.open().enter_token()
    page = editor.page
    a = fx.isolated(source="detected")[0]
    editor.click_marking(a)
    editor.key("r")
    # The database goes away just as the changeset is sent (the store's answer to an outage).
    outage = json.dumps({"type": "urn:lanemap:problem:store-unavailable", "title": "Service Unavailable",
                         "status": 503, "detail": "the database is unavailable; retry shortly"})

    def post_fails(route):
        if route.request.method != "POST":
            return route.continue_()
        return route.fulfill(status=503, body=outage, headers={
            "Content-Type": "application/problem+json", "Retry-After": "5", "X-Request-ID": "outage-1"})

    page.route("**/changesets", post_fails)
    editor.save("during an outage")
    page.wait_for_function("document.getElementById('toast').textContent.includes('outage-1')")
    assert page.text_content("#toast") == ("Save failed, your edits are kept: 503: the database is unavailable; "
                                           "retry shortly (request outage-1)")
    assert editor.unsaved() == 1
    page.unroute("**/changesets", post_fails)
    editor.responses.clear()  # the 503 above was the test's own
    # Once the database is back, the same edits save.
    editor.save("after the outage")
    page.wait_for_function("document.getElementById('unsaved').textContent === '0 unsaved'")
    got = httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{a}").json()["properties"]
    assert got["status"] == "rejected"


def test_unsaved_edits_survive_a_reload_and_a_crash(editor, fx, server):
    editor.open().enter_token()
    page = editor.page
    a = fx.isolated(source="detected")[0]
    editor.click_marking(a)
    editor.key("r")
    editor.key("n")
    x, y = editor.px(*fx.lonlat(a))
    page.mouse.click(x + 80, y + 80)
    assert editor.unsaved() == 2

    page.reload()
    editor.wait_loaded()
    assert editor.unsaved() == 2
    assert editor.pending()[a]["cur"]["status"] == "rejected"
    assert not page.is_visible("#readonly")  # the token is kept for the browser session
    assert "Restored 2 unsaved edits" in page.text_content("#toast")
    editor.key("Control+z")  # the undo history came back too
    assert editor.unsaved() == 1

    # A crash: the tab goes away without unloading; a new tab finds the edits (but no token).
    page.close(run_before_unload=False)
    editor.open(editor.new_page())
    page = editor.page
    assert editor.unsaved() == 1
    assert page.is_visible("#readonly")
    assert page.is_disabled("#save")

    # Discarding forgets them for good.
    page.once("dialog", lambda d: d.accept())
    page.click("#discard")
    assert editor.unsaved() == 0
    assert page.evaluate("localStorage.length") == 0
    assert api_get(server, f"/collections/{fx.map_id}/changesets")["numberMatched"] == 1


def test_review_queue_steps_through_detections_by_score(editor, fx):
    editor.open().enter_token()
    page = editor.page
    n = len(fx.detected)
    progress = f"Saved: 0 of {n} detections reviewed (0.0 %; 0 accepted, 0 rejected), {n} to go."
    page.wait_for_function(f"document.getElementById('review-progress').textContent === {json.dumps(progress)}")
    page.click("#review-start")
    q = fx.detected
    page.wait_for_function(f"lanemapEditor.state.selection.has('{q[0]}')")
    # Leaflet may animate the zoom: the view is final once the animation ends.
    page.wait_for_function("lanemapEditor.map.getZoom() === 21 && !lanemapEditor.map._animatingZoom")
    c = page.evaluate("lanemapEditor.map.getCenter()")
    assert metres_between(c["lng"], c["lat"], *fx.lonlat(q[0])) < 0.05
    assert f"1 of {len(q)}" in page.text_content("#review-status")

    editor.key("a")
    assert editor.selection() == {q[1]}
    editor.key("r")
    assert editor.selection() == {q[2]}
    editor.key(" ")
    assert editor.selection() == {q[3]}
    assert f"4 of {len(q)}" in page.text_content("#review-status")
    pend = editor.pending()
    assert (pend[q[0]]["cur"]["status"], pend[q[1]]["cur"]["status"]) == ("accepted", "rejected")
    assert set(pend) == {q[0], q[1]}
    editor.key("Escape")
    assert page.is_hidden("#review-stop")
    editor.key("Control+z")
    assert set(editor.pending()) == {q[0]}
    # the progress counts what is saved
    assert page.text_content("#review-progress") == progress
    editor.save("one accepted")
    progress = (f"Saved: 1 of {n} detections reviewed ({100 / n:.1f} %; 1 accepted, 0 rejected), "
                f"{n - 1} to go.")  # fmt: skip
    page.wait_for_function(f"document.getElementById('review-progress').textContent === {json.dumps(progress)}")


def test_the_review_queue_comes_a_page_at_a_time(editor, fx, server):
    """The queue is read from the server a page at a time (``GET .../review/queue``), the next page
    asked for before the reviewer reaches it; the reviewer steps through every detection in score
    order across pages, and one that someone else decided in a page not yet read is not shown."""
    editor.open().enter_token()
    page = editor.page
    q = fx.detected
    assert len(q) > 12
    page.evaluate("Object.assign(lanemapEditor.reviewPaging, {page: 4, prefetch: 2})")
    # someone else accepts the tenth, in the third page, before the review reads it
    with server.client(headers=server.auth) as c:
        f = c.get(f"/collections/{fx.map_id}/items/{q[9]}")
        r = c.patch(f"/collections/{fx.map_id}/items/{q[9]}", json={"properties": {"status": "accepted"}},
                    headers={"If-Match": f.headers["etag"], "Content-Type": "application/merge-patch+json"})  # fmt: skip
        assert r.status_code == 200, r.text
    page.click("#review-start")
    page.wait_for_function(f"lanemapEditor.state.selection.has('{q[0]}')")
    assert page.evaluate("lanemapEditor.state.review.queue.length") == 4
    assert f"1 of {len(q) - 1}:" in page.text_content("#review-status")
    seen = [q[0]]
    for k in range(1, len(q) - 1):
        editor.key("a" if k == 3 else " ")
        page.wait_for_function("lanemapEditor.state.selection.size === 1 && !lanemapEditor.state.review?.waiting"
                               f" && !lanemapEditor.state.selection.has('{seen[-1]}')")  # fmt: skip
        seen.append(next(iter(editor.selection())))
        loaded = page.evaluate("lanemapEditor.state.review.queue.length")
        assert loaded <= min(k + 2 + 4, len(q) - 1), (k, loaded)  # read ahead by a page, no further
    assert seen == [i for i in q if i != q[9]]
    assert editor.pending()[q[2]]["cur"]["status"] == "accepted"
    editor.key(" ")
    page.wait_for_selector("#review-status:has-text('Review done')")
    pages = [u for s_, u in editor.responses if "/review/queue" in u]
    assert len(pages) == -(-(len(q) - 1) // 4) + ((len(q) - 1) % 4 == 0), pages


def test_the_sure_detections_are_decided_at_once_by_score(editor, fx, server):
    """*Count* says what a review by score would do without writing; *Apply…* asks, then writes
    one changeset, which the history lists and the progress counts; a read-only page cannot apply."""
    editor.open()
    page = editor.page
    assert page.is_disabled("#bulk-apply")
    editor.enter_token()
    scores = {i: fx.features[i]["properties"]["score"] for i in fx.detected}
    want_acc = sum(v >= 0.8 for v in scores.values())
    want_rej = sum(v < 0.3 for v in scores.values())
    assert want_acc and want_rej
    # how the unreviewed scores spread: ten bars, one per tenth
    page.wait_for_selector("#review-scores span")
    titles = page.eval_on_selector_all("#review-scores span", "bars => bars.map(b => b.title)")
    assert titles == [f"score {k / 10:.1f}–{(k + 1) / 10:.1f}: {sum(k / 10 <= v < (k + 1) / 10 for v in scores.values())}"
                      " unreviewed" for k in range(10)]  # fmt: skip
    page.fill("#bulk-accept", "0.8")
    page.fill("#bulk-reject", "0.3")
    page.click("#bulk-preview")
    page.wait_for_selector(f"#bulk-status:has-text('{want_acc} to accept and {want_rej} to reject in the map.')")
    assert api_get(server, f"/collections/{fx.map_id}/changesets")["numberMatched"] == 1  # the import only
    asked = []
    page.once("dialog", lambda d: (asked.append(d.message), d.accept()))
    page.click("#bulk-apply")
    page.wait_for_selector(f"#bulk-status:has-text('Accepted {want_acc} and rejected {want_rej} in the map')")
    assert asked == [f"Accept {want_acc} and reject {want_rej} unreviewed detections in the map, as one changeset?"]
    got = {f["id"]: f["properties"]["status"] for f in api_get(server, f"/collections/{fx.map_id}/items",
                                                                  limit=10000)["features"]}  # fmt: skip
    for i, v in scores.items():
        assert got[i] == ("accepted" if v >= 0.8 else "rejected" if v < 0.3 else "unreviewed"), (i, v)
    page.wait_for_selector("#history-list li:has-text('review by score in the map')")
    n = len(fx.detected)
    page.wait_for_selector(f"#review-progress:has-text('Saved: {want_acc + want_rej} of {n} detections reviewed')")
    # the page shows the new statuses without a reload
    page.wait_for_function(f"lanemapEditor.state.server.get('{fx.detected[0]}')?.status === 'rejected'")


def test_a_district_is_reviewed_on_its_own(editor, fx):
    """*this view only*: the progress counts the detections in view, the queue holds only them, and
    the review by score decides only them."""
    editor.open().enter_token()
    page = editor.page
    a = fx.isolated(source="detected")[0]
    lon, lat = fx.lonlat(a)
    page.evaluate(f"void lanemapEditor.map.setView([{lat}, {lon}], 20, {{animate: false}})")
    page.check("#review-in-view")
    b = page.evaluate("(() => { const b = lanemapEditor.map.getBounds(); "
                      "return [b.getWest(), b.getSouth(), b.getEast(), b.getNorth()]; })()")  # fmt: skip
    inside = [i for i in fx.detected if b[0] <= fx.lonlat(i)[0] <= b[2] and b[1] <= fx.lonlat(i)[1] <= b[3]]
    assert 0 < len(inside) < len(fx.detected)
    page.wait_for_selector(f"#review-progress:has-text('Saved, in view: 0 of {len(inside)} detections reviewed')")
    page.fill("#bulk-accept", "0")  # every detection in view
    page.fill("#bulk-reject", "0")
    page.click("#bulk-preview")
    page.wait_for_selector(f"#bulk-status:has-text('{len(inside)} to accept and 0 to reject in view.')")
    page.click("#review-start")  # (the queue then centres each detection in turn)
    page.wait_for_selector(f"#review-status:has-text('1 of {len(inside)}:')")


def review_list(page, path, places: dict) -> None:
    """Write a GeoJSON list of places to ``path`` and give it to the review panel's list field."""
    path.write_text(json.dumps(places))
    page.set_input_files("#review-file", str(path))


def lanemapEditor_zoom(page) -> int:
    return page.evaluate("lanemapEditor.map.getZoom()")


def test_a_list_of_places_is_reviewed_in_its_order(editor, fx, tmp_path):
    """A GeoJSON list such as ``lanemap evaluate --errors`` writes: a point whose id is a
    marking of the map selects it for A / R; another is a place to look at (a missed
    marking); each is ringed on the map until the review ends."""
    editor.open().enter_token()
    page = editor.page
    false_id = fx.detected[0]
    lon0, lat0 = fx.lonlat(false_id)
    missed = (lon0 + 4e-5, lat0 + 2e-5)
    places = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "id": false_id, "geometry": {"type": "Point", "coordinates": [lon0, lat0]},
         "properties": {"error": "false", "kind": "dash"}},
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": list(missed)},
         "properties": {"error": "missed", "kind": "stop_line", "length_m": 3.5}},
        {"type": "Feature", "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 1]]},
         "properties": {}},
    ]}  # fmt: skip
    review_list(page, tmp_path / "errors.geojson", places)
    page.wait_for_function(f"lanemapEditor.state.selection.has('{false_id}')")
    status = page.text_content("#review-status")
    assert "1 of 2 in errors.geojson" in status and f"marking {false_id} matches nothing true" in status
    rings = "lanemapEditor.state.review.overlay.getLayers().length"
    assert page.evaluate(rings) == 2
    editor.key("r")  # rejects the false marking and goes on to the missed one
    assert editor.pending()[false_id]["cur"]["status"] == "rejected"
    assert editor.selection() == set()
    # the view pans there (Leaflet may animate it)
    page.wait_for_function(
        """([lon, lat]) => { const c = lanemapEditor.map.getCenter();
             return Math.hypot((c.lng - lon) * 73000, (c.lat - lat) * 111000) < 0.05; }""", arg=list(missed))
    assert lanemapEditor_zoom(page) == 21
    assert "2 of 2 in errors.geojson: a stop_line, 3.50 m the map misses" in page.text_content("#review-status")
    editor.key("a")  # nothing to accept here: the review stays on this place
    assert "2 of 2" in page.text_content("#review-status")
    page.evaluate("(globalThis.listRings = lanemapEditor.state.review.overlay, true)")
    assert page.evaluate("lanemapEditor.map.hasLayer(listRings)")
    editor.key("n")  # adds the missed marking as the list describes it, and goes on
    added = [v["cur"] for k, v in editor.pending().items() if k != false_id]
    assert len(added) == 1 and added[0]["kind"] == "stop_line" and added[0]["length_m"] == 3.5
    assert (added[0]["lon"], added[0]["lat"]) == pytest.approx(missed, abs=1e-9)
    assert "Review done: 2 places of errors.geojson" in page.text_content("#review-status")
    assert page.evaluate("lanemapEditor.state.review") is None
    assert not page.evaluate("lanemapEditor.map.hasLayer(listRings)")
    # a file that is not GeoJSON says so and starts nothing
    bad = tmp_path / "bad.geojson"
    bad.write_text("{no")
    page.set_input_files("#review-file", str(bad))
    page.wait_for_function("document.getElementById('review-status').textContent.includes('could not be read')")
    assert page.evaluate("lanemapEditor.state.review") is None


def test_a_listed_marking_the_page_has_not_loaded_is_fetched(editor, fx, tmp_path):
    """A large map is loaded by view: a listed marking the page does not hold yet is asked
    of the server, and only one the server does not have is called gone."""
    editor.open().enter_token()
    page = editor.page
    fid = fx.detected[1]
    page.evaluate(f"lanemapEditor.state.known.delete('{fid}')")
    lon, lat = fx.lonlat(fid)
    places = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "id": fid, "geometry": {"type": "Point", "coordinates": [lon, lat]}, "properties": {}},
        {"type": "Feature", "id": "999999999", "geometry": {"type": "Point", "coordinates": [lon, lat]},
         "properties": {}},
    ]}  # fmt: skip
    review_list(page, tmp_path / "places.geojson", places)
    page.wait_for_function(f"lanemapEditor.state.selection.has('{fid}')")
    assert f"1 of 2 in places.geojson: marking {fid}" in page.text_content("#review-status")
    editor.key(" ")
    page.wait_for_function("document.getElementById('review-status').textContent.startsWith('2 of 2')")
    assert "marking 999999999, not in this map (any more)" in page.text_content("#review-status")
    assert editor.selection() == set()


def test_the_map_is_scored_against_a_survey_and_its_errors_reviewed(editor, fx, server, tmp_path):
    """A survey file is scored on the server (``POST .../evaluate``); the page shows the figures
    and steps through the false and missed markings."""
    editor.open().enter_token()
    page = editor.page
    kept = [f for f in fx.features.values() if f["properties"]["status"] != "rejected"]
    false_id = fx.detected[0]
    lon0, lat0 = fx.lonlat(false_id)
    survey = [f for f in kept if f["id"] != false_id]
    survey.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": [lon0 + 5e-5, lat0]},
                   "properties": {"kind": "dash", "length_m": 3.0, "bearing_deg": 90.0}})  # fmt: skip
    body = {"type": "FeatureCollection", "features": survey}
    want = httpx.post(f"{server.base_url}/collections/{fx.map_id}/evaluate", json=body, timeout=60).json()
    errs = want["errors"]["features"]
    assert false_id in {str(f.get("id")) for f in errs if f["properties"]["error"] == "false"}
    assert sum(f["properties"]["error"] == "missed" for f in errs) == 1
    path = tmp_path / "survey.geojson"
    path.write_text(json.dumps(body))
    page.set_input_files("#score-file", str(path))
    page.wait_for_function("document.getElementById('score-summary').textContent.startsWith('Against')")
    summary = page.text_content("#score-summary")
    assert (f"precision {want['precision']:.3f} ({want['correct_detections']} of {want['detections']}"
            in summary), summary  # fmt: skip
    assert f"recall {want['recall']:.3f} ({want['found']} of {want['true_markings']} found)" in summary
    n = len(want["errors"]["features"])
    page.wait_for_function("lanemapEditor.state.review !== null")
    assert f"1 of {n} in the errors against survey.geojson" in page.text_content("#review-status")
    firsts = want["errors"]["features"][0]
    if firsts.get("id") is not None:
        assert editor.selection() == {str(firsts["id"])}
    assert page.evaluate("lanemapEditor.state.review.overlay.getLayers().length") == n


def test_box_selection_attributes_and_revert(editor, fx, server):
    editor.open().enter_token()
    page = editor.page
    # Shift+drag a box: every marking whose centroid is inside is selected.
    box = page.locator("#map").bounding_box()
    a = (box["x"] + box["width"] * 0.3, box["y"] + box["height"] * 0.3)
    b = (box["x"] + box["width"] * 0.6, box["y"] + box["height"] * 0.6)
    (w, n), (e, s) = editor.lonlat(*a), editor.lonlat(*b)
    inside = {fid for fid in fx.features if w <= fx.lonlat(fid)[0] <= e and s <= fx.lonlat(fid)[1] <= n}
    assert len(inside) >= 5
    page.keyboard.down("Shift")
    editor.drag(a, b)
    page.keyboard.up("Shift")
    assert editor.selection() == inside
    assert page.text_content("#sel-count") == str(len(inside))
    # Shift+click takes one out of the selection, and puts it back.
    one_in = sorted(set(fx.isolated(2.0)) & inside)[0]
    editor.click_marking(one_in, shift=True)
    assert editor.selection() == inside - {one_in}
    editor.click_marking(one_in, shift=True)
    assert editor.selection() == inside
    page.click("#act-accept")
    n_changed = sum(fx.features[f]["properties"]["status"] != "accepted" for f in inside)
    assert editor.unsaved() == n_changed

    # Edit one marking's attributes in the form.
    one = fx.isolated(source="imported")[0]
    editor.click_marking(one)
    page.fill("#attrs input[name=length_m]", "4.5")
    page.fill("#attrs input[name=kind]", "stop_line")
    page.click("#attrs-apply")
    cur = editor.pending()[one]["cur"]
    assert (cur["length_m"], cur["kind"]) == (4.5, "stop_line")
    editor.save("accept a box, fix one")
    page.wait_for_function("document.getElementById('unsaved').textContent === '0 unsaved'")
    got = httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{one}").json()["properties"]
    assert (got["length_m"], got["kind"]) == (4.5, "stop_line")

    # Revert that changeset from the history panel.
    cs = api_get(server, f"/collections/{fx.map_id}/changesets")["changesets"][0]
    page.once("dialog", lambda d: d.accept("undo the box"))
    page.click(f"#history-list li[data-changeset='{cs['id']}'] .revert")
    page.wait_for_selector(f"#history-list li[data-changeset='{int(cs['id']) + 1}']")
    newest = api_get(server, f"/collections/{fx.map_id}/changesets")["changesets"][0]
    assert (newest["reverts"], newest["comment"]) == (cs["id"], "undo the box")
    got = httpx.get(f"{server.base_url}/collections/{fx.map_id}/items/{one}").json()["properties"]
    assert got["length_m"] == pytest.approx(fx.features[one]["properties"]["length_m"])


def test_maps_are_picked_from_the_list(editor, fx, server):
    other = server.new_map(prefix="tiny")
    r = httpx.post(f"{server.base_url}/collections/{other}/import", headers=server.auth,
                   json={"type": "FeatureCollection", "features": [feature(8.4 + i * 1e-4, 49.0, length_m=3.0)
                                                                   for i in range(3)]})  # fmt: skip
    assert r.status_code == 201
    editor.open()
    page = editor.page
    assert page.evaluate("lanemapEditor.layer.size") == len(fx.features)
    assert page.is_hidden("#no-imagery")
    page.select_option("#map-select", other)
    page.wait_for_function("lanemapEditor.layer.size === 3")
    assert page.is_visible("#no-imagery")
    assert not [u for _, u in editor.responses if f"/collections/{other}/imagery/tiles/" in u]
    assert f"map={other}" in page.evaluate("location.hash")
    cs = api_get(server, f"/collections/{other}/changesets")["changesets"]
    page.wait_for_selector(f"#history-list li[data-changeset='{cs[0]['id']}']")
    assert page.locator("#history-list li").count() == len(cs) == 1
    # The address keeps map and view: a reload comes back to them.
    page.reload()
    page.wait_for_function("lanemapEditor.layer.size === 3")
    assert page.input_value("#map-select") == other


def test_the_ground_the_map_speaks_for_is_outlined(editor, fx, server):
    """Ticking "the ground the map speaks for" outlines the map's coverage as localization draws it:
    by the hull every marking lies inside; a map that says ``markings`` shows a smaller outline, and
    the outline goes with the box unticked."""
    editor.open()
    page = editor.page
    assert page.text_content("#coverage-name") == "hull" and page.evaluate("lanemapEditor.coverage()") is None
    page.check("#coverage-show")
    page.wait_for_function("document.getElementById('coverage-status').textContent.startsWith('hull:')")
    inside = page.evaluate("""(pts) => { const b = lanemapEditor.coverage().getBounds();
        return pts.every(([lon, lat]) => b.contains([lat, lon])); }""", [fx.lonlat(f) for f in fx.features])
    assert inside
    hull_area = api_get(server, f"/collections/{fx.map_id}/coverage")["properties"]["area_m2"]
    assert f"revision {api_get(server, f'/collections/{fx.map_id}')['revision']}" in page.text_content(
        "#coverage-status")
    r = httpx.patch(f"{server.base_url}/collections/{fx.map_id}", json={"coverage": "markings"}, headers=server.auth)
    assert r.status_code == 200, r.text
    page.reload()
    editor.wait_loaded()
    assert page.text_content("#coverage-name") == "markings"
    page.check("#coverage-show")
    page.wait_for_function("document.getElementById('coverage-status').textContent.startsWith('markings:')")
    parts = api_get(server, f"/collections/{fx.map_id}/coverage")["properties"]["area_m2"]
    assert parts < hull_area
    page.uncheck("#coverage-show")
    page.wait_for_function("lanemapEditor.coverage() === null")
    assert page.text_content("#coverage-status") == ""
    assert not editor.errors, editor.errors


def test_a_server_that_wants_a_token_for_reads(browser, window, tmp_path):
    srv = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data",
                       env={"LANEMAP_READ_TOKEN_REQUIRED": "1", "LANEMAP_READ_TOKENS": "fleet-secret"})  # fmt: skip
    try:
        fx = create_map(srv, window, "locked")
        ed = Editor(browser, srv, fx)
        page = ed.page
        page.goto(f"{srv.base_url}/editor/")
        page.wait_for_function("document.getElementById('view-status').textContent.includes('token')")
        assert page.evaluate("lanemapEditor.layer.size") == 0
        # A read token (a vehicle's, say) shows the map and changes nothing.
        page.fill("#token-input", "fleet-secret")
        page.click("#token-use")
        ed.wait_loaded()
        assert page.evaluate("lanemapEditor.layer.size") == len(fx.features)
        assert page.is_visible("#readonly") and "may only read" in page.text_content("#readonly")
        assert page.text_content("#who") == "read-only token"
        assert page.is_disabled("#mode-add")
        fid = fx.isolated()[0]
        ed.click_marking(fid)
        assert ed.selection() == {fid}
        ed.key("a")
        assert ed.unsaved() == 0 and "may only read" in page.text_content("#toast")
        # Tiles are fetched with the token too.
        page.wait_for_function("document.querySelectorAll('.leaflet-tile-loaded').length >= 4")
        assert any(st == 200 and "/imagery/tiles/" in u for st, u in ed.responses)
        # Forgotten, the write token takes its place; a reload keeps what each token may do.
        page.click("#token-forget")
        ed.enter_token()
        assert page.text_content("#who") == "editing" and page.is_enabled("#mode-add")
        page.reload()
        ed.wait_loaded()
        assert page.is_hidden("#readonly") and page.is_enabled("#mode-add")
        ed.close()
    finally:
        srv.stop()


def test_edit_session_logic(browser, server):
    """The editor's local edit model (edits.js) on its own: what gets saved, undo, rebase."""
    page = browser.new_page()
    page.goto(f"{server.base_url}/conformance")
    out = page.evaluate(
        """async () => {
             const { EditSession } = await import('/editor/edits.js');
             const s = new EditSession('k', null);
             const m = (id, extra) => ({ id, lon: 8.4, lat: 49.0, weight: 10, length_m: 3, width_m: 0.15,
                                         bearing_deg: 10, score: 0.4, kind: 'dash', source: 'detected',
                                         status: 'unreviewed', version: '1', ...extra });
             const a = m('1'), b = m('2'), c = m('3');
             const r = {};
             s.apply('reject', [{ base: a, cur: { ...a, status: 'rejected' } }]);
             s.apply('move', [{ base: b, cur: { ...b, lon: 8.5 } }]);
             s.apply('move back', [{ base: b, cur: { ...b } }]);       // back where it was: no edit left
             r.afterMoveBack = s.count;
             const n = { ...m(s.newLocalId()), version: null, source: 'manual' };
             s.apply('add', [{ base: null, cur: n }]);
             s.apply('delete new', [{ base: { id: n.id }, cur: null }]);  // added and deleted: nothing
             s.apply('delete', [{ base: c, cur: null }]);
             r.count = s.count;
             r.body = s.toChangeset('c').body;
             s.undo(); s.undo();                                       // the delete, then 'delete new'
             r.afterUndo = [...s.pending.keys()].sort();
             s.redo();
             r.afterRedo = [...s.pending.keys()];
             // Someone else widened marking 1 (version 2) and deleted marking 3.
             s.redo();
             r.dropped = s.rebase(new Map([['1', { ...a, width_m: 0.3, version: '2' }], ['3', null]]));
             r.rebased = s.toChangeset('again').body.changes;
             return r;
           }"""
    )
    page.close()
    assert out["afterMoveBack"] == 1
    assert out["count"] == 2
    assert out["body"] == {"comment": "c", "changes": [
        {"op": "update", "id": "1", "version": "1", "patch": {"properties": {"status": "rejected"}}},
        {"op": "delete", "id": "3", "version": "1"},
    ]}  # fmt: skip
    assert out["afterUndo"] == ["1", "new-1"] and out["afterRedo"] == ["1"]
    assert out["dropped"] == ["3"]
    assert out["rebased"] == [
        {"op": "update", "id": "1", "version": "2", "patch": {"properties": {"status": "rejected"}}},
    ]


def test_editor_is_served_without_a_cdn(server):
    """Every file the page loads comes from the service itself."""
    r = httpx.get(f"{server.base_url}/editor", follow_redirects=True)
    assert r.status_code == 200 and "lanemap editor" in r.text
    assert "http://" not in r.text and "https://" not in r.text
    for path in ("vendor/leaflet/leaflet.js", "vendor/leaflet/leaflet.css", "vendor/leaflet/LICENSE",
                 "main.js", "edits.js", "api.js", "layer.js", "editor.css"):  # fmt: skip
        assert httpx.get(f"{server.base_url}/editor/{path}").status_code == 200, path
    landing = httpx.get(f"{server.base_url}/").json()
    assert any(link["href"].endswith("/editor/") for link in landing["links"])
