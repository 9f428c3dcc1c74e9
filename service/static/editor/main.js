// The map editor: wires the API, the local edit session and the Leaflet map together.

import { Api, ApiError } from './api.js';
import { EditSession, isLocalId } from './edits.js';
import { MarkingLayer, fromEnds, isLowScore, lengthDoubts, metres } from './layer.js';

const L = globalThis.L;
const $ = (id) => document.getElementById(id);

/** Below this zoom a large map's markings are not loaded (too many to be useful on screen). */
const MIN_LOAD_ZOOM = 17;
/** A map with at most this many markings is drawn at any zoom. */
const SMALL_MAP = 20000;
const REVIEW_ZOOM = 21;
const TOKEN_KEY = 'lanemap.token';
const TOKEN_WRITES_KEY = 'lanemap.token.writes';

const api = new Api(new URL('../', document.baseURI), () => state.token);

const state = {
  token: sessionStorage.getItem(TOKEN_KEY),
  tokenWrites: sessionStorage.getItem(TOKEN_WRITES_KEY) !== '0', // a read token may not edit
  mapId: null,
  collection: null,
  session: null,
  server: new Map(), // id -> marking, as last loaded for the view
  known: new Map(), // id -> every server marking seen (edits start from these)
  selection: new Set(),
  conflicts: new Map(), // id -> conflict from the server
  mode: 'select',
  review: null, // {queue: [marking], index, total, next, loading, waiting} or, for a list, {queue: [place], index, list, overlay}
  lengthDoubts: new Map(), // id -> typical length (m) of detections whose length the localizer doubts
  gesture: null, // a drag, box or dash being drawn
  afterGesture: false, // the click that ends a drag is not a click
  loadAbort: null,
  loadedBounds: null, // the box whose markings are loaded (null: none, or the whole map)
  revision: null, // the map's revision that the loaded markings are at least as new as
  loadedAll: false, // the whole map is loaded (a small one), not a box of it
  polling: false,
  writes: 0, // saves and reverts under way: their own changes are not someone else's
  writeSeq: 0,
  historyOffset: 0,
};

// ---------------------------------------------------------------- the map
const map = L.map('map', {
  zoomControl: true,
  boxZoom: false,
  minZoom: 3, // fixed, so that a basemap's own limits do not move the view while a map opens
  maxZoom: 23,
  zoomSnap: 1, // whole zoom levels: fractional ones leave seams between imagery tiles
  preferCanvas: true,
  attributionControl: true,
}).setView([49.0, 8.4], 4);
map.attributionControl.setPrefix('<a href="https://leafletjs.com">Leaflet</a>');
let imagery = null;

/** Imagery tiles fetched with the token when there is one (a server may want it for reads too). */
const ImageryLayer = L.TileLayer.extend({
  createTile(coords, done) {
    const img = document.createElement('img');
    img.alt = '';
    img.setAttribute('role', 'presentation');
    fetch(this.getTileUrl(coords), { headers: api.headers() })
      .then((r) => (r.ok ? r.blob() : Promise.reject(new Error(`tile: HTTP ${r.status}`))))
      .then((blob) => {
        img.onload = () => {
          URL.revokeObjectURL(img.src);
          done(null, img);
        };
        img.onerror = (err) => done(err, img);
        img.src = URL.createObjectURL(blob);
      })
      .catch((err) => done(err, img));
    return img;
  },
});

const layer = new MarkingLayer(map, { onDown: onMarkingDown, onClick: onMarkingClick });

/** Why nothing can be changed: no token, or a token that may only read. */
function readOnlyText(what = 'edit this map') {
  return state.token
    ? `Read-only: this token may only read. Forget it and enter a write token to ${what}.`
    : `Read-only: enter the API token to ${what}.`;
}

function canEdit() {
  return Boolean(state.token && state.tokenWrites && state.mapId);
}

function toast(text, kind = 'info') {
  const el = $('toast');
  el.textContent = text;
  el.className = `show ${kind}`;
  clearTimeout(toast.timer);
  toast.timer = setTimeout(() => (el.className = ''), kind === 'error' ? 8000 : 3500);
}

function problemText(err) {
  if (!(err instanceof ApiError)) return String(err?.message || err);
  // A server error is the operator's to look into: the request ID finds it in the server's log.
  const ref = err.status >= 500 && err.requestId ? ` (request ${err.requestId})` : '';
  return `${err.status}: ${err.message}${ref}`;
}

// ---------------------------------------------------------------- markings: as edited
/** A marking as it is locally: the edited one if there is an unsaved edit, else the server's. */
function current(id) {
  id = String(id);
  const e = state.session?.pending.get(id);
  if (e) return e.cur;
  return state.known.get(id) ?? null;
}

function base(id) {
  id = String(id);
  const e = state.session?.pending.get(id);
  return e ? e.base : state.known.get(id) ?? null;
}

function visibleMarkings() {
  const out = new Map();
  for (const [id, m] of state.server) {
    const cur = state.session.effective(id, m);
    if (cur) out.set(id, cur);
  }
  for (const m of state.session.localMarkings()) out.set(String(m.id), m);
  return [...out.values()];
}

function render() {
  if (!state.session) return;
  const edited = state.session.pending;
  const markings = visibleMarkings();
  state.lengthDoubts = lengthDoubts(markings);
  layer.draw(markings, (m) => {
    const id = String(m.id);
    if (state.conflicts.has(id)) return 'conflict';
    if (state.selection.has(id)) return 'selected';
    if (edited.has(id)) return 'edited';
    if (isLowScore(m)) return 'low';
    if (state.lengthDoubts.has(id)) return 'length';
    return null;
  });
  renderSelection();
}

// ---------------------------------------------------------------- edits
function edit(label, changes) {
  if (!canEdit()) {
    toast(readOnlyText('edit'), 'error');
    return false;
  }
  const done = state.session.apply(label, changes);
  if (done) render();
  return done;
}

function setStatus(ids, status) {
  const changes = [];
  for (const id of ids) {
    const m = current(id);
    if (m && m.status !== status) changes.push({ base: base(id), cur: { ...m, status } });
  }
  return edit(`${status} ${changes.length}`, changes);
}

function deleteMarkings(ids) {
  // A new marking has no base: the pending entry names it.
  const changes = [...ids].filter((id) => current(id)).map((id) => ({ base: base(id) ?? { id }, cur: null }));
  const ok = edit(`delete ${changes.length}`, changes);
  if (ok) state.selection.clear();
  render();
  return ok;
}

function moveMarking(id, lon, lat) {
  const m = current(id);
  return edit('move', [{ base: base(id), cur: { ...m, lon, lat } }]);
}

/** Typical values of nearby markings for a new one: length, weight, bearing of the nearest. */
function defaultsNear(lon, lat) {
  const all = visibleMarkings().filter((m) => m.status !== 'rejected');
  let nearest = null;
  let best = 30; // metres
  for (const m of all) {
    const [e, n] = metres(lon, lat, m.lon, m.lat);
    const d = Math.hypot(e, n);
    if (d < best) [best, nearest] = [d, m];
  }
  const median = (xs, fallback) => {
    const v = xs.filter((x) => Number.isFinite(x) && x > 0).sort((a, b) => a - b);
    return v.length ? v[v.length >> 1] : fallback;
  };
  const dashes = all.filter((m) => m.kind === 'dash');
  return {
    length_m: median(dashes.map((m) => m.length_m), 3.0),
    width_m: median(all.map((m) => m.width_m), 0.15),
    weight: median(all.map((m) => m.weight), 100),
    bearing_deg: nearest ? nearest.bearing_deg : 0,
  };
}

function addMarking(props) {
  const id = state.session.newLocalId();
  const d = defaultsNear(props.lon, props.lat);
  const m = {
    id, weight: d.weight, length_m: d.length_m, width_m: d.width_m, bearing_deg: d.bearing_deg,
    score: null, kind: 'dash', source: 'manual', status: 'accepted', version: null, ...props,
  };
  if (edit('add', [{ base: null, cur: m }])) {
    state.selection = new Set([id]);
    render();
  }
}

function undo() {
  const r = state.session.undo();
  if (r) {
    toast(`Undone: ${r.label}`);
    render();
  }
}

function redo() {
  const r = state.session.redo();
  if (r) {
    toast(`Redone: ${r.label}`);
    render();
  }
}

// ---------------------------------------------------------------- mouse: select, box, move, add
function onMarkingDown(m, e) {
  const ev = e.originalEvent;
  if (ev.button !== 0) return;
  state.afterGesture = false;
  if (state.mode === 'add' && canEdit()) {
    ev._stopped = true;
    L.DomEvent.stopPropagation(ev);
    startDash(e);
    return;
  }
  if (state.mode !== 'select' || !canEdit() || ev.shiftKey) return;
  // Press on a marking: a drag moves it (the map must not pan meanwhile).
  ev._stopped = true;
  L.DomEvent.stopPropagation(ev);
  state.gesture = { kind: 'move', id: String(m.id), m0: current(m.id), from: e.latlng, p0: e.containerPoint, moved: false };
  map.dragging.disable();
}

function onMarkingClick(m, e) {
  if (state.mode !== 'select' || state.afterGesture) return;
  const id = String(m.id);
  if (e.originalEvent.shiftKey || e.originalEvent.ctrlKey || e.originalEvent.metaKey) {
    if (state.selection.has(id)) state.selection.delete(id);
    else state.selection.add(id);
  } else {
    state.selection = new Set([id]);
  }
  render();
}

function startDash(e) {
  const line = L.polyline([e.latlng, e.latlng], { color: '#2ee86f', weight: 4, dashArray: '6 4', interactive: false }).addTo(map);
  state.gesture = { kind: 'dash', a: e.latlng, p0: e.containerPoint, line };
  map.dragging.disable();
}

map.on('mousedown', (e) => {
  const ev = e.originalEvent;
  if (ev._stopped || ev.button !== 0) return;
  state.afterGesture = false;
  if (state.mode === 'add' && canEdit()) {
    startDash(e);
  } else if (state.mode === 'select' && ev.shiftKey) {
    const rect = L.rectangle(L.latLngBounds(e.latlng, e.latlng), { color: '#fff', weight: 1, dashArray: '4 3', fillOpacity: 0.08, interactive: false }).addTo(map);
    state.gesture = { kind: 'box', a: e.latlng, p0: e.containerPoint, rect };
    map.dragging.disable();
  }
});

map.on('mousemove', (e) => {
  const g = state.gesture;
  if (!g) return;
  if (g.kind === 'move') {
    if (!g.moved && e.containerPoint.distanceTo(g.p0) < 3) return;
    g.moved = true;
    const dLon = e.latlng.lng - g.from.lng;
    const dLat = e.latlng.lat - g.from.lat;
    layer.preview({ ...g.m0, lon: g.m0.lon + dLon, lat: g.m0.lat + dLat });
  } else if (g.kind === 'box') {
    g.rect.setBounds(L.latLngBounds(g.a, e.latlng));
  } else if (g.kind === 'dash') {
    g.line.setLatLngs([g.a, e.latlng]);
  }
});

function endGesture(e) {
  const g = state.gesture;
  if (!g) return;
  state.gesture = null;
  // A box hardly drawn is a Shift+click: the click that follows toggles the marking.
  const tiny = g.kind === 'box' && (!e || e.containerPoint.distanceTo(g.p0) < 4);
  state.afterGesture = g.kind === 'move' ? g.moved : !tiny;
  map.dragging.enable();
  if (g.kind === 'move') {
    if (g.moved && e) {
      const lon = g.m0.lon + (e.latlng.lng - g.from.lng);
      const lat = g.m0.lat + (e.latlng.lat - g.from.lat);
      moveMarking(g.id, lon, lat);
      state.selection = new Set([g.id]);
    }
    render();
  } else if (g.kind === 'box') {
    g.rect.remove();
    if (!e || tiny) return;
    // Not the rectangle's bounds: the map throttles mousemove, the last one may be missing.
    const bounds = L.latLngBounds(g.a, e.latlng);
    const ids = visibleMarkings().filter((m) => bounds.contains([m.lat, m.lon])).map((m) => String(m.id));
    if (!e.originalEvent.ctrlKey && !e.originalEvent.metaKey) state.selection.clear();
    for (const id of ids) state.selection.add(id);
    render();
  } else if (g.kind === 'dash') {
    g.line.remove();
    if (!e) return;
    if (e.containerPoint.distanceTo(g.p0) < 6) {
      addMarking({ lon: g.a.lng, lat: g.a.lat });
    } else {
      addMarking(fromEnds(g.a.lng, g.a.lat, e.latlng.lng, e.latlng.lat));
    }
  }
}

map.on('mouseup', endGesture);
document.addEventListener('mouseup', (ev) => {
  // Released outside the map: finish where the pointer left it.
  if (state.gesture && !map.getContainer().contains(ev.target)) endGesture(null);
});

map.on('click', (e) => {
  if (state.afterGesture) return;
  if (state.mode === 'select' && !e.originalEvent.shiftKey && state.selection.size) {
    state.selection.clear();
    render();
  }
});

function setMode(mode) {
  if (mode === 'add' && !canEdit()) {
    toast(readOnlyText('add markings'), 'error');
    return;
  }
  state.mode = mode;
  $('mode-select').classList.toggle('active', mode === 'select');
  $('mode-add').classList.toggle('active', mode === 'add');
  map.getContainer().classList.toggle('adding', mode === 'add');
}

// ---------------------------------------------------------------- loading a map and the view
async function loadMaps() {
  const maps = await api.collections();
  const sel = $('map-select');
  sel.replaceChildren(...maps.map((c) => new Option(`${c.title} (${c.id})`, c.id)));
  if (!maps.length) {
    $('view-status').textContent = 'The server has no maps yet.';
    return;
  }
  const wanted = new URLSearchParams(location.hash.slice(1)).get('map');
  const id = maps.some((c) => c.id === wanted) ? wanted : maps[0].id;
  sel.value = id;
  await openMap(id, true);
}

async function openMap(mapId, fromHash = false) {
  stopReview();
  state.mapId = mapId;
  state.revision = null;
  state.collection = await api.collection(mapId);
  state.revision = state.collection.revision;
  state.server.clear();
  state.known.clear();
  state.selection.clear();
  state.conflicts.clear();
  $('conflict').hidden = true;
  $('history-list').replaceChildren();
  state.session = new EditSession(`lanemap.edits.${location.host}.${mapId}`);
  state.session.onChange(updateCounters);
  // Unsaved edits are known markings too (they may lie outside the first view).
  for (const [id, e] of state.session.pending) if (e.base) state.known.set(id, e.base);
  if (state.session.restored) toast(`Restored ${state.session.restored} unsaved edits of map ${mapId}.`);
  updateCounters();

  if (imagery) imagery.remove();
  imagery = null;
  const images = await api.imagery(mapId).catch(() => null);
  if (images?.length !== 0) { // unknown (the listing failed): try the tiles anyway
    imagery = new ImageryLayer(api.tileUrl(mapId), {
      maxZoom: 23, maxNativeZoom: 22, minZoom: 10, tileSize: 256, attribution: `imagery of ${mapId}`,
    }).addTo(map);
  }
  $('no-imagery').hidden = images?.length !== 0;
  showCoverage();

  const h = new URLSearchParams(location.hash.slice(1));
  const bbox = state.collection.extent?.spatial?.bbox?.[0];
  if (fromHash && h.get('map') === mapId && h.has('z')) {
    map.setView([+h.get('lat'), +h.get('lon')], +h.get('z'), { animate: false });
  } else if (bbox) {
    map.fitBounds([[bbox[1], bbox[0]], [bbox[3], bbox[2]]], { maxZoom: 20, padding: [20, 20], animate: false });
  }
  await loadView();
  loadHistory(true);
  loadProgress();
  applyTokenState();
}

/** The map's coverage, outlined when "the ground the map speaks for" is ticked: where the
 * localizer's check at a map's edge draws it (an imagery gap or the end of a mapped part shows
 * as a hole or an edge of the outline). */
let coverage = null;
async function showCoverage() {
  const mapId = state.mapId;
  $('coverage-name').textContent = state.collection?.coverage ?? '';
  if (coverage) coverage.remove();
  coverage = null;
  if (!$('coverage-show').checked || !mapId) {
    $('coverage-status').textContent = '';
    return;
  }
  try {
    const f = await api.coverage(mapId);
    if (mapId !== state.mapId || !$('coverage-show').checked) return;
    if (coverage) coverage.remove();
    coverage = null;
    if (!f.geometry) {
      $('coverage-status').textContent = 'The map has no area yet.';
      return;
    }
    coverage = L.geoJSON(f, { interactive: false, style: { color: '#f72585', weight: 2, dashArray: '6 4', fillOpacity: 0.05 } }).addTo(map);
    const km2 = f.properties.area_m2 / 1e6;
    $('coverage-status').textContent = `${f.properties.coverage}: ${km2 < 1 ? `${Math.round(f.properties.area_m2).toLocaleString()} m²` : `${km2.toFixed(2)} km²`} at revision ${f.properties.revision}.`;
  } catch (err) {
    $('coverage-status').textContent = `The coverage could not be drawn: ${err.message}`;
  }
}
$('coverage-show').addEventListener('change', () => showCoverage());

async function loadView() {
  if (!state.mapId) return;
  const mapId = state.mapId;
  const total = state.collection?.numberOfFeatures ?? Infinity;
  state.loadAbort?.abort();
  if (map.getZoom() < MIN_LOAD_ZOOM && total > SMALL_MAP) {
    state.server.clear();
    state.loadedBounds = null;
    state.loadedAll = false;
    $('view-status').textContent = `Zoom in to see the markings (${total} in this map).`;
    render();
    return;
  }
  const ctl = new AbortController();
  state.loadAbort = ctl;
  const b = map.getBounds().pad(0.25);
  const bbox = total <= SMALL_MAP ? null : [
    Math.max(b.getWest(), -180), Math.max(b.getSouth(), -90), Math.min(b.getEast(), 180), Math.min(b.getNorth(), 90),
  ];
  $('view-status').textContent = 'Loading markings…';
  try {
    const items = await api.items(mapId, bbox, {
      signal: ctl.signal,
      onPage: (n, of) => ($('view-status').textContent = `Loading markings… ${n} of ${of}`),
    });
    if (ctl.signal.aborted || mapId !== state.mapId) return;
    state.server = new Map(items.map((m) => [m.id, m]));
    state.loadedBounds = bbox ? b : null;
    state.loadedAll = !bbox;
    for (const m of items) state.known.set(m.id, m);
    $('view-status').textContent = `${items.length} markings ${bbox ? 'in view' : 'in this map'}.`;
    render();
    document.body.dataset.loaded = String(Date.now());
  } catch (err) {
    if (err.name === 'AbortError') return;
    $('view-status').textContent = `Markings could not be loaded: ${problemText(err)}`;
  }
}

let moveTimer = null;
map.on('moveend', () => {
  if (!state.mapId) return;
  const c = map.getCenter();
  history.replaceState(null, '', `#map=${encodeURIComponent(state.mapId)}&z=${map.getZoom()}&lat=${c.lat.toFixed(7)}&lon=${c.lng.toFixed(7)}`);
  if ((state.collection?.numberOfFeatures ?? Infinity) <= SMALL_MAP && state.server.size) return;
  // Panning within the loaded (padded) box needs no reload.
  if (state.loadedBounds && map.getZoom() >= MIN_LOAD_ZOOM && state.loadedBounds.contains(map.getBounds())) return;
  clearTimeout(moveTimer);
  moveTimer = setTimeout(loadView, 250);
});

$('map-select').addEventListener('change', (e) => openMap(e.target.value));

// An address typed or pasted in (or Back): go to its map and view.
window.addEventListener('hashchange', () => {
  const h = new URLSearchParams(location.hash.slice(1));
  const id = h.get('map');
  if (id && id !== state.mapId && [...$('map-select').options].some((o) => o.value === id)) {
    $('map-select').value = id;
    openMap(id, true);
  } else if (h.has('z')) {
    map.setView([+h.get('lat'), +h.get('lon')], +h.get('z'));
  }
});

// ---------------------------------------------------------------- selection panel
function renderSelection() {
  const ids = [...state.selection].filter((id) => current(id));
  const one = ids.length === 1 ? current(ids[0]) : null;
  $('sel-none').hidden = ids.length > 0;
  $('sel-many').hidden = ids.length < 2;
  $('sel-count').textContent = String(ids.length);
  $('sel-actions').hidden = ids.length === 0;
  const form = $('attrs');
  form.hidden = !one;
  for (const b of $('sel-actions').querySelectorAll('button')) b.disabled = !canEdit();
  if (!one) return;
  if (form.dataset.id !== String(one.id) || form.dataset.sig !== JSON.stringify(one)) {
    form.dataset.id = String(one.id);
    form.dataset.sig = JSON.stringify(one);
    $('attr-id').textContent = isLocalId(one.id) ? `${one.id} (not saved)` : one.id;
    $('attr-source').textContent = one.source;
    $('attr-score').textContent = one.score == null ? '–' : one.score.toFixed(3);
    $('attr-version').textContent = one.version ?? '–';
    form.status.value = one.status;
    form.kind.value = one.kind ?? '';
    form.length_m.value = round(one.length_m, 3);
    form.width_m.value = round(one.width_m, 3);
    form.bearing_deg.value = round(one.bearing_deg, 2);
    form.weight.value = round(one.weight, 1);
  }
  for (const el of form.elements) el.disabled = !canEdit();
}

function round(v, digits) {
  return v == null ? '' : String(Math.round(v * 10 ** digits) / 10 ** digits);
}

$('attrs').addEventListener('submit', (e) => {
  e.preventDefault();
  const form = e.target;
  const id = form.dataset.id;
  const m = current(id);
  if (!m) return;
  const num = (name, min) => {
    const v = Number(form[name].value);
    if (!Number.isFinite(v) || v < min) throw new Error(`${name} must be a number ≥ ${min}`);
    return v;
  };
  try {
    const next = {
      ...m,
      status: form.status.value,
      kind: form.kind.value.trim() || null,
      length_m: num('length_m', 0),
      width_m: num('width_m', 0),
      bearing_deg: ((num('bearing_deg', -360) % 180) + 180) % 180,
      weight: num('weight', 1e-9),
    };
    edit('edit attributes', [{ base: base(id), cur: next }]);
    form.dataset.sig = '';
    render();
  } catch (err) {
    toast(err.message, 'error');
  }
});

$('act-accept').addEventListener('click', () => setStatus(state.selection, 'accepted'));
$('act-reject').addEventListener('click', () => setStatus(state.selection, 'rejected'));
$('act-delete').addEventListener('click', () => deleteMarkings(state.selection));

// ---------------------------------------------------------------- counters, undo, save
function updateCounters() {
  const s = state.session;
  const n = s ? s.count : 0;
  $('unsaved').textContent = `${n} unsaved`;
  $('unsaved').classList.toggle('dirty', n > 0);
  $('undo').disabled = !s?.undoStack.length || !canEdit();
  $('redo').disabled = !s?.redoStack.length || !canEdit();
  $('save').disabled = n === 0 || !canEdit();
  $('discard').disabled = n === 0;
  if (s?.persistFailed) toast('The browser has no room to keep your unsaved edits over a reload: save soon.', 'error');
}

$('undo').addEventListener('click', undo);
$('redo').addEventListener('click', redo);
$('discard').addEventListener('click', () => {
  if (!confirm(`Forget ${state.session.count} unsaved edits?`)) return;
  state.session.clear();
  state.conflicts.clear();
  $('conflict').hidden = true;
  render();
});

function openSave() {
  if (!canEdit() || !state.session.count) return;
  const n = state.session.count;
  $('save-count').textContent = `${n} changed marking${n === 1 ? '' : 's'}`;
  $('save-dialog').returnValue = ''; // Esc keeps the last value: it must not mean "save"
  $('save-dialog').showModal();
  $('save-comment').focus();
}
$('save').addEventListener('click', openSave);
$('save-dialog').addEventListener('close', () => {
  if ($('save-dialog').returnValue === 'save') save($('save-comment').value.trim());
});

async function save(comment) {
  const s = state.session;
  const { body, ids } = s.toChangeset(comment);
  $('save').disabled = true;
  state.writes++;
  state.writeSeq++;
  try {
    const res = await api.saveChangeset(state.mapId, body);
    const created = res.results.filter((r) => r.op === 'create').map((r) => r.id);
    // The saved markings are the server's now; keep the selection on them.
    const newIds = new Map(ids.map((id, i) => [id, res.results[i].id]));
    state.selection = new Set([...state.selection].map((id) => newIds.get(id) ?? id));
    s.clear();
    state.conflicts.clear();
    $('conflict').hidden = true;
    $('save-comment').value = '';
    toast(`Saved changeset ${res.changeset}: ${res.results.length} markings (${created.length} new).`);
    await afterOwnWrite();
  } catch (err) {
    if (err instanceof ApiError && (err.status === 409 || err.status === 412)) {
      showConflict(err.problem);
    } else if (err instanceof ApiError && err.status === 401) {
      toast('The token was refused: enter it again. Your edits are kept.', 'error');
      forgetToken();
    } else if (err instanceof ApiError && err.status === 403) {
      toast('This token may only read: enter a write token to save. Your edits are kept.', 'error');
      forgetToken();
    } else {
      toast(`Save failed, your edits are kept: ${problemText(err)}`, 'error');
    }
  } finally {
    state.writes--;
    updateCounters();
  }
}

function showConflict(problem, { live = false } = {}) {
  const list = problem.conflicts || (problem.conflicting_ids || []).map((id) => ({ id, reason: 'version' }));
  state.conflicts = new Map(list.map((c) => [String(c.id), c]));
  $('conflict-title').textContent = live ? 'Someone else changed markings you are editing' : 'Save refused: conflicting edits';
  $('conflict-text').textContent = live
    ? `${list.length} of your edited markings changed on the server since you loaded them; saving now would be refused.`
    : `${list.length} of your edited markings changed on the server since you loaded them. Nothing was saved.`;
  $('conflict-list').replaceChildren(...list.map((c) => {
    const li = document.createElement('li');
    const a = document.createElement('a');
    a.href = '#';
    a.textContent = `marking ${c.id}`;
    a.addEventListener('click', (e) => {
      e.preventDefault();
      const m = current(c.id) ?? base(c.id);
      if (m) map.setView([m.lat, m.lon], Math.max(map.getZoom(), 20));
      state.selection = new Set([String(c.id)]);
      render();
    });
    li.append(a, c.reason === 'missing' ? ': deleted by someone else'
      : `: now at version ${c.actual_version}, you edited version ${c.expected_version}`);
    return li;
  }));
  $('conflict').hidden = false;
  render();
  toast(live ? 'Someone else changed markings you are editing. Your edits are kept.'
    : 'Save refused: some markings changed on the server. Your edits are kept.', 'error');
}

// ---------------------------------------------------------------- others' edits, as they are saved
/** How often the editor asks for the map's changes since its revision, ms (`?live=` in the address). */
const LIVE_MS = Number(new URLSearchParams(location.search).get('live')) || 5000;

/** Whether a marking belongs to what is loaded: the whole map, or the loaded box. */
function inLoaded(m) {
  return state.loadedBounds ? state.loadedBounds.contains([m.lat, m.lon]) : state.loadedAll;
}

/** The conflict of an unsaved edit `e` of marking `id` with the server's marking `m` now (null:
 * deleted there), or null where there is none: it changed there since the edit's base. */
function conflictWith(id, e, m) {
  if (!e?.base || (m && String(m.version) === String(e.base.version))) return null;
  return m ? { id, reason: 'version', expected_version: e.base.version, actual_version: m.version }
    : { id, reason: 'missing', expected_version: e.base.version };
}

/**
 * Take in what others saved since the loaded revision: their markings replace the loaded ones,
 * deleted ones go, and a marking with an unsaved edit here that changed there is a conflict
 * now, not at the next save.
 */
async function followChanges() {
  if (!state.mapId || state.revision == null || state.polling || state.writes || document.hidden) return;
  const mapId = state.mapId;
  const seq = state.writeSeq;
  state.polling = true;
  try {
    const { revision, now, count } = await api.changes(mapId, state.revision, { max: follow.max });
    // A save or revert of this editor began meanwhile: the next round sees the map after it.
    if (mapId !== state.mapId || revision === state.revision || seq !== state.writeSeq || state.writes) return;
    if (now === null) {
      await readAgain(mapId, revision, count);
      return;
    }
    const conflicts = new Map(state.conflicts);
    for (const [id, m] of now) {
      const e = state.session.pending.get(id);
      const conflict = conflictWith(id, e, m);
      if (conflict) conflicts.set(id, conflict);
      if (m) {
        if (inLoaded(m)) state.server.set(id, m);
        else state.server.delete(id);
        if (state.known.has(id) || inLoaded(m)) state.known.set(id, m);
      } else {
        state.server.delete(id);
        if (!e) {
          state.known.delete(id);
          state.selection.delete(id);
        }
      }
    }
    state.revision = revision;
    $('view-status').textContent = `${now.size} marking${now.size === 1 ? '' : 's'} changed on the server; up to date with revision ${revision}.`;
    if (conflicts.size > state.conflicts.size) showConflict({ conflicts: [...conflicts.values()] }, { live: true });
    else render();
    renderSelection();
    loadHistory(true);
    loadProgress();
  } catch (err) {
    if (err instanceof ApiError && err.status === 409) {
      toast(`The server cannot list map ${mapId}'s changes since this page loaded it (made anew, or its old changes pruned): loaded again.`, 'error');
      openMap(mapId);
    }
    // Anything else (the network, a restart): the next round asks again.
  } finally {
    state.polling = false;
  }
}
// More changes than `follow.max` at once (a review by score across a city) are not read one by
// one: the page reads again what it shows instead (readAgain).
const follow = { max: 5000 };

/**
 * After `count` changes since the loaded revision, too many to read: the markings with unsaved
 * edits are read again one by one (those that changed are conflicts, as with the change feed),
 * the view is loaded again, and a running review queue goes on from its detection with what the
 * server holds now. What else was known of the map is forgotten, to be read when needed.
 */
async function readAgain(mapId, revision, count) {
  const edited = [...state.session.pending].filter(([, e]) => e.base).map(([id]) => id);
  const fresh = edited.length <= READ_AGAIN_EDITS
    ? new Map(await Promise.all(edited.map(async (id) => [id, await api.item(mapId, id)]))) : new Map();
  if (mapId !== state.mapId) return;
  const conflicts = new Map(state.conflicts);
  for (const [id, m] of fresh) {
    const conflict = conflictWith(id, state.session.pending.get(id), m);
    if (conflict) conflicts.set(id, conflict);
  }
  const keep = new Map();
  for (const [id, e] of state.session.pending) if (e.base) keep.set(id, fresh.get(id) ?? state.known.get(id) ?? e.base);
  state.known = keep;
  state.revision = revision;
  const r = state.review;
  if (r && !r.list) {
    const at = r.queue[r.index];
    if (at) state.known.set(String(at.id), at);
    r.queue.length = Math.max(r.index + 1, 0);
    r.next = api.reviewQueueUrl(mapId, r.box, { after: at, pageSize: reviewPaging.page });
  }
  await loadView();
  $('view-status').textContent = `${count.toLocaleString()} markings changed on the server: ${$('view-status').textContent} Up to date with revision ${revision}.`;
  if (conflicts.size > state.conflicts.size) showConflict({ conflicts: [...conflicts.values()] }, { live: true });
  else render();
  renderSelection();
  loadHistory(true);
  loadProgress();
}
/** Unsaved edits of markings read again one by one after too many changes; beyond, the save finds the conflicts. */
const READ_AGAIN_EDITS = 200;

setInterval(followChanges, LIVE_MS);
document.addEventListener('visibilitychange', () => { if (!document.hidden) followChanges(); });

$('conflict-rebase').addEventListener('click', async () => {
  const ids = [...state.conflicts.keys()];
  try {
    const now = new Map(await Promise.all(ids.map(async (id) => [id, await api.item(state.mapId, id)])));
    for (const [id, m] of now) if (m) state.known.set(id, m);
    const dropped = state.session.rebase(now);
    state.conflicts.clear();
    $('conflict').hidden = true;
    await loadView();
    toast(`Reloaded ${ids.length} markings and re-applied your edits${dropped.length ? `; ${dropped.length} were deleted on the server and your edits of them dropped` : ''}. Check them and save again.`);
  } catch (err) {
    toast(`Reload failed: ${problemText(err)}`, 'error');
  }
});
$('conflict-close').addEventListener('click', () => {
  $('conflict').hidden = true;
  state.conflicts.clear();
  render();
});

// ---------------------------------------------------------------- review queue
async function startReview() {
  if (!state.mapId) return;
  $('review-status').textContent = 'Loading unreviewed detections…';
  try {
    const box = reviewBox();
    const page = await api.reviewQueue(state.mapId, box, { pageSize: reviewPaging.page });
    const r = { queue: [], index: -1, total: page.total, next: null, mapId: state.mapId, box };
    addReviewPage(r, page);
    state.review = r;
    $('review-start').hidden = true;
    $('review-stop').hidden = false;
    setMode('select');
    nextReview();
  } catch (err) {
    $('review-status').textContent = `Review could not start: ${problemText(err)}`;
  }
}

// The queue comes a page at a time, the next one asked for while `prefetch` are left: a city's
// detections would fit neither in a page's memory nor in a reviewer's patience for their download.
const reviewPaging = { page: 500, prefetch: 100 };

function addReviewPage(r, page) {
  for (const m of page.items) state.known.set(m.id, m);
  r.queue.push(...page.items);
  r.next = page.next;
}

/** The review queue's next page, once (a promise while it loads). */
function moreReview(r) {
  if (!r.loading && r.next) {
    const from = r.next; // the queue may be read again meanwhile (readAgain): this page is then not its
    r.loading = api.reviewQueue(r.mapId, null, { next: from })
      .then((page) => { if (state.review === r && r.next === from) addReviewPage(r, page); })
      .finally(() => { r.loading = null; });
  }
  return r.loading;
}

/** Centre the view on ``latlng`` at ``zoom``, after a running zoom animation (Leaflet drops a
 * new view asked for during one, as when a reviewer decides faster than the map zooms). */
function goTo(latlng, zoom) {
  if (map._animatingZoom) map.once('zoomend', () => map.setView(latlng, zoom));
  else map.setView(latlng, zoom);
}

// A list of places from a GeoJSON file: its points are visited in order. A point whose
// feature id is a marking of this map selects it (A / R decide on it); any other point
// is a place to look at, for instance a marking the map misses (N adds one there).
const LIST_COLOURS = { false: '#ff3b30', missed: '#0a84ff' };

function listPlaces(fc) {
  const feats = fc && fc.type === 'FeatureCollection' && Array.isArray(fc.features) ? fc.features : null;
  if (!feats) throw new Error('not a GeoJSON FeatureCollection');
  return feats
    .filter((f) => f && f.geometry && f.geometry.type === 'Point' && Array.isArray(f.geometry.coordinates)
      && f.geometry.coordinates.slice(0, 2).every(Number.isFinite))
    .map((f) => ({
      lon: f.geometry.coordinates[0],
      lat: f.geometry.coordinates[1],
      id: f.id == null ? null : String(f.id),
      props: f.properties || {},
    }));
}

async function reviewFile(file) {
  if (!state.mapId || !file) return;
  let places;
  try {
    places = listPlaces(JSON.parse(await file.text()));
  } catch (err) {
    $('review-status').textContent = `${file.name} could not be read: ${err.message}`;
    return;
  }
  startListReview(file.name, places);
}

/** Score the saved map against a survey on the server, then step through its false and missed markings. */
async function scoreAgainst(file) {
  if (!state.mapId || !file) return;
  $('score-file').value = '';
  let truth;
  try {
    truth = JSON.parse(await file.text());
  } catch (err) {
    $('review-status').textContent = `${file.name} could not be read: ${err.message}`;
    return;
  }
  $('score-summary').textContent = `Scoring the saved map against ${file.name}…`;
  let res;
  try {
    res = await api.evaluate(state.mapId, truth);
  } catch (err) {
    $('score-summary').textContent = `Scoring failed: ${problemText(err)}`;
    return;
  }
  const share = (v) => (v == null ? 'n/a' : v.toFixed(3));
  const unsaved = state.session.pending.size;
  $('score-summary').textContent = `Against ${file.name}: precision ${share(res.precision)} `
    + `(${res.correct_detections} of ${res.detections} markings on a true one), recall ${share(res.recall)} `
    + `(${res.found} of ${res.true_markings} found)`
    + (unsaved ? `; ${unsaved} unsaved edits are not in it` : '');
  const places = listPlaces(res.errors);
  if (!places.length) {
    stopReview();
    $('review-status').textContent = `Nothing false or missed against ${file.name}.`;
    return;
  }
  startListReview(`the errors against ${file.name}`, places);
}

function startListReview(name, places) {
  if (!places.length) {
    $('review-status').textContent = `${name} has no points to visit.`;
    return;
  }
  stopReview();
  const overlay = L.layerGroup(places.map((p) => L.circleMarker([p.lat, p.lon], {
    radius: 12, weight: 2, fill: false, interactive: false,
    color: LIST_COLOURS[p.props.error] || '#ff9f0a',
  }))).addTo(map);
  state.review = { queue: places, index: -1, list: name, overlay };
  $('review-start').hidden = true;
  $('review-stop').hidden = false;
  setMode('select');
  nextReview();
}

function placeText(p, m) {
  const kind = p.props.kind || 'marking';
  const length = Number.isFinite(p.props.length_m) ? `, ${p.props.length_m.toFixed(2)} m` : '';
  if (p.props.error === 'missed') return `a ${kind}${length} the map misses: N adds it as listed`;
  if (m && p.props.error === 'false') return `marking ${m.id} matches nothing true: reject or delete it`;
  if (m) return `marking ${m.id}`;
  return p.id ? `marking ${p.id}, not in this map (any more)` : `a place (${kind}${length})`;
}

async function nextListPlace(r) {
  r.index += 1;
  if (r.index >= r.queue.length) {
    $('review-status').textContent = `Review done: ${r.queue.length} places of ${r.list}.`;
    stopReview(false);
    return;
  }
  const p = r.queue[r.index];
  let m = p.id ? current(p.id) : null;
  if (p.id && !m) {
    // A large map is loaded by view: ask the server before calling the marking gone.
    try {
      const found = await api.item(state.mapId, p.id);
      if (found) state.known.set(found.id, found);
    } catch (err) {
      toast(`Marking ${p.id} could not be loaded: ${problemText(err)}`, 'error');
    }
    if (state.review !== r) return; // the review ended meanwhile
    m = current(p.id);
  }
  state.selection = new Set(m ? [String(m.id)] : []);
  goTo([p.lat, p.lon], REVIEW_ZOOM);
  render();
  $('review-status').textContent = `${r.index + 1} of ${r.queue.length} in ${r.list}: ${placeText(p, m)}`;
}

function nextReview() {
  const r = state.review;
  if (!r) return;
  if (r.list) {
    nextListPlace(r);
    return;
  }
  do r.index += 1;
  while (r.index < r.queue.length && (current(r.queue[r.index].id)?.status ?? 'gone') !== 'unreviewed');
  if (r.index >= r.queue.length && r.next) {
    // past what is loaded: wait for the next page, deciding nothing meanwhile
    r.index = r.queue.length - 1;
    r.waiting = true;
    $('review-status').textContent = 'Loading more unreviewed detections…';
    moreReview(r).then(() => {
      r.waiting = false;
      if (state.review === r) nextReview();
    }, (err) => {
      r.failed = true;
      if (state.review === r) $('review-status').textContent = `The review queue could not go on: ${problemText(err)}; A, R or Space tries again`;
    });
    return;
  }
  if (r.index >= r.queue.length) {
    $('review-status').textContent = `Review done: ${r.queue.length} detections in the queue.`;
    stopReview(false);
    return;
  }
  if (r.next && r.queue.length - r.index <= reviewPaging.prefetch) moreReview(r)?.catch(() => {}); // tried again when needed
  const m = current(r.queue[r.index].id);
  state.selection = new Set([String(m.id)]);
  goTo([m.lat, m.lon], REVIEW_ZOOM);
  render();
  const typical = state.lengthDoubts.get(String(m.id));
  const doubt = typical === undefined ? ''
    : `; ${m.length_m.toFixed(2)} m long where ${typical.toFixed(2)} m is typical: a dash cut short or run long? Fix its ends, or set its kind if it is right`;
  $('review-status').textContent = `${r.index + 1} of ${Math.max(r.total, r.queue.length)}: marking ${m.id}, score ${m.score == null ? '–' : m.score.toFixed(3)}${doubt}`;
}

/** At a listed place with no marking of the map, add the marking the list describes
 * (its kind, length, width and bearing where given) and go on. False if there is none to add. */
function addListedMarking() {
  const r = state.review;
  const p = r && r.list ? r.queue[r.index] : null;
  if (!p || (p.id && current(p.id)) || !canEdit()) return false;
  const props = { lon: p.lon, lat: p.lat };
  if (typeof p.props.kind === 'string' && p.props.kind) props.kind = p.props.kind;
  for (const key of ['length_m', 'width_m']) {
    if (Number.isFinite(p.props[key]) && p.props[key] > 0) props[key] = p.props[key];
  }
  if (Number.isFinite(p.props.bearing_deg)) props.bearing_deg = ((p.props.bearing_deg % 360) + 360) % 360;
  addMarking(props);
  nextReview();
  return true;
}

function reviewDecide(status) {
  const r = state.review;
  if (!r) return;
  if (r.waiting) {
    // the next page is loading, or failed to: nothing to decide on until it is here
    if (r.failed) {
      r.waiting = r.failed = false;
      nextReview();
    }
    return;
  }
  if (r.index >= r.queue.length) return;
  const id = r.list ? r.queue[r.index].id : String(r.queue[r.index].id);
  if (status && r.list && !(id && current(id))) {
    toast('No marking of this map here to decide on: Space goes on.');
    return;
  }
  if (status && !setStatus([id], status)) return;
  nextReview();
}

function stopReview(clearText = true) {
  if (state.review?.overlay) state.review.overlay.remove();
  $('review-file').value = '';
  state.review = null;
  $('review-start').hidden = false;
  $('review-stop').hidden = true;
  if (clearText) $('review-status').textContent = '';
}

// ---------------------------------------------------------------- review by score
function bulkBody(dryRun) {
  const num = (id) => ($(id).value.trim() === '' ? null : Number($(id).value));
  const body = { accept_from: num('bulk-accept'), reject_below: num('bulk-reject'), dry_run: dryRun };
  const box = reviewBox();
  if (box) body.bbox = box.map((v) => v.toFixed(7)).join(',');
  return body;
}

async function bulkReview(dryRun) {
  if (!state.mapId || (!dryRun && !canEdit())) return;
  const body = bulkBody(dryRun);
  const where = body.bbox ? 'in view' : 'in the map';
  try {
    if (!dryRun) {
      const n = await api.reviewByScore(state.mapId, { ...body, dry_run: true });
      if (!confirm(`Accept ${n.accepted} and reject ${n.rejected} unreviewed detections ${where}, as one changeset?`)) return;
      body.comment = `review by score ${where}`;
      state.writes++;
      state.writeSeq++;
    }
    try {
      const res = await api.reviewByScore(state.mapId, body);
      if (dryRun || res.changeset == null) {
        $('bulk-status').textContent = `${res.accepted} to accept and ${res.rejected} to reject ${where}.`;
        return;
      }
      $('bulk-status').textContent = `Accepted ${res.accepted} and rejected ${res.rejected} ${where} (changeset #${res.changeset}).`;
      await afterOwnWrite();
    } finally {
      if (!dryRun) state.writes--;
    }
  } catch (err) {
    $('bulk-status').textContent = `Review by score failed: ${problemText(err)}`;
  }
}
$('review-in-view').addEventListener('change', loadProgress);
map.on('moveend', () => { if ($('review-in-view').checked && !state.review) loadProgress(); });
$('bulk-preview').addEventListener('click', () => bulkReview(true));
$('bulk-apply').addEventListener('click', () => bulkReview(false));

$('review-start').addEventListener('click', startReview);
$('review-file').addEventListener('change', (e) => reviewFile(e.target.files[0]));
$('score-file').addEventListener('change', (e) => scoreAgainst(e.target.files[0]));
$('review-stop').addEventListener('click', () => stopReview());

// ---------------------------------------------------------------- history
/** After this page wrote to the map (a save, a revert, a review by score): the map's revision,
 * the markings in view, the history and the review's progress as the server now has them. */
async function afterOwnWrite() {
  state.collection = await api.collection(state.mapId);
  state.revision = state.collection.revision;
  showCoverage();
  await loadView();
  loadHistory(true);
  loadProgress();
}

/** The box the review works in: the view's (minLon, minLat, maxLon, maxLat) when "this view
 * only" is ticked, else null (the whole map). */
function reviewBox() {
  if (!$('review-in-view').checked) return null;
  const b = map.getBounds();
  return [b.getWest(), b.getSouth(), b.getEast(), b.getNorth()];
}

/** How far the review of the saved map (or of the view) has come, from the server's count of its detections. */
async function loadProgress() {
  if (!state.mapId) return;
  const mapId = state.mapId;
  const box = reviewBox();
  try {
    const sm = await api.summary(mapId, box);
    if (mapId !== state.mapId) return;
    const d = sm.review.detections;
    const total = d.unreviewed + d.accepted + d.rejected;
    const fmt = (v) => v.toLocaleString('en');
    const where = box ? 'in view' : 'in this map';
    $('review-progress').textContent = total === 0 ? `No detections to review ${where}.`
      : `Saved${box ? ', in view' : ''}: ${fmt(total - d.unreviewed)} of ${fmt(total)} detections reviewed `
        + `(${(100 * sm.review.reviewedShare).toFixed(1)} %; ${fmt(d.accepted)} accepted, `
        + `${fmt(d.rejected)} rejected), ${fmt(d.unreviewed)} to go.`;
    // How the unreviewed detections' scores spread: where to set the thresholds of a review by score.
    const bins = sm.review.unreviewedScores;
    const top = Math.max(...bins.map((b) => b.count));
    $('review-scores').hidden = top === 0;
    $('review-scores').replaceChildren(...bins.map((b) => {
      const bar = document.createElement('span');
      bar.style.height = `${top ? (100 * b.count) / top : 0}%`;
      bar.className = b.count ? '' : 'empty';
      bar.title = `score ${b.min.toFixed(1)}–${b.max.toFixed(1)}: ${b.count.toLocaleString('en')} unreviewed`;
      return bar;
    }));
  } catch (err) {
    $('review-progress').textContent = `Review progress could not be loaded: ${problemText(err)}`;
  }
}

async function loadHistory(reset = false) {
  if (!state.mapId) return;
  const mapId = state.mapId;
  const offset = reset ? 0 : state.historyOffset;
  try {
    const page = await api.changesets(mapId, { limit: 30, offset });
    if (mapId !== state.mapId) return; // another map was opened meanwhile
    if (reset) $('history-list').replaceChildren();
    state.historyOffset = offset + page.numberReturned;
    $('history-list').append(...page.changesets.map(historyItem));
    $('history-more').hidden = state.historyOffset >= page.numberMatched;
  } catch (err) {
    $('history-list').textContent = `History could not be loaded: ${problemText(err)}`;
  }
}

function historyItem(c) {
  const li = document.createElement('li');
  li.dataset.changeset = c.id;
  const when = new Date(c.at);
  const counts = [c.created && `+${c.created}`, c.updated && `~${c.updated}`, c.deleted && `−${c.deleted}`].filter(Boolean).join(' ');
  const head = document.createElement('div');
  head.className = 'h-head';
  head.innerHTML = '<b></b> <span class="who"></span> <time></time> <span class="counts"></span>';
  head.querySelector('b').textContent = `#${c.id}`;
  head.querySelector('.who').textContent = c.who;
  head.querySelector('time').textContent = when.toLocaleString();
  head.querySelector('time').dateTime = c.at;
  head.querySelector('.counts').textContent = counts;
  head.querySelector('.counts').title = `${c.created} created, ${c.updated} updated, ${c.deleted} deleted`;
  const comment = document.createElement('div');
  comment.className = 'comment';
  comment.textContent = (c.comment || '(no comment)') + (c.reverts ? ` · reverts #${c.reverts}` : '');
  const show = document.createElement('button');
  show.className = 'small';
  show.textContent = 'Show';
  show.addEventListener('click', () => showChangeset(c.id));
  const revert = document.createElement('button');
  revert.className = 'small revert';
  revert.textContent = 'Revert';
  revert.disabled = !canEdit();
  revert.addEventListener('click', () => revertChangeset(c));
  li.append(head, comment, show, revert);
  return li;
}

async function showChangeset(id) {
  try {
    const cs = await api.changeset(state.mapId, id);
    const pts = cs.edits.flatMap((e) => [e.before, e.after]).filter(Boolean)
      .filter((m) => Number.isFinite(m.lon) && Number.isFinite(m.lat)).map((m) => [m.lat, m.lon]);
    if (pts.length) map.fitBounds(L.latLngBounds(pts), { maxZoom: 21, padding: [40, 40] });
    state.selection = new Set(cs.edits.map((e) => e.feature_id).filter(Boolean));
    render();
  } catch (err) {
    toast(`Changeset ${id} could not be loaded: ${problemText(err)}`, 'error');
  }
}

async function revertChangeset(c) {
  if (!canEdit()) return;
  const comment = prompt(`Revert changeset #${c.id} (${c.comment || 'no comment'})? Comment:`, `revert #${c.id}`);
  if (comment === null) return;
  state.writes++;
  state.writeSeq++;
  try {
    const res = await api.revert(state.mapId, c.id, comment);
    toast(`Changeset #${c.id} reverted by #${res.changeset}.`);
    await afterOwnWrite();
  } catch (err) {
    const ids = err.problem?.conflicting_ids;
    toast(`Revert refused: ${problemText(err)}${ids ? ` (markings ${ids.join(', ')} changed since)` : ''}`, 'error');
  } finally {
    state.writes--;
  }
}

$('history-refresh').addEventListener('click', () => loadHistory(true));
$('history-more').addEventListener('click', () => loadHistory(false));

// ---------------------------------------------------------------- the token
function applyTokenState() {
  const has = Boolean(state.token);
  const writes = has && state.tokenWrites;
  $('readonly').hidden = writes;
  $('readonly').textContent = readOnlyText();
  $('token-form').hidden = has;
  $('token-forget').hidden = !has;
  $('who').hidden = !has;
  $('who').textContent = writes ? 'editing' : has ? 'read-only token' : '';
  document.body.classList.toggle('readonly', !writes);
  for (const id of ['mode-add', 'bulk-apply']) $(id).disabled = !writes;
  for (const b of document.querySelectorAll('#history-list .revert')) b.disabled = !writes;
  if (!writes && state.mode === 'add') setMode('select');
  updateCounters();
  renderSelection();
}

function forgetToken() {
  state.token = null;
  state.tokenWrites = true;
  sessionStorage.removeItem(TOKEN_KEY);
  sessionStorage.removeItem(TOKEN_WRITES_KEY);
  applyTokenState();
}

$('token-form').addEventListener('submit', async (e) => {
  e.preventDefault();
  const token = $('token-input').value.trim();
  if (!token) return;
  let may;
  try {
    may = await api.checkToken(token);
  } catch (err) {
    toast(`The token could not be checked: ${problemText(err)}`, 'error');
    return;
  }
  if (!may) {
    toast('The server does not accept this token.', 'error');
    return;
  }
  state.token = token;
  state.tokenWrites = may === 'write';
  sessionStorage.setItem(TOKEN_KEY, token);
  sessionStorage.setItem(TOKEN_WRITES_KEY, state.tokenWrites ? '1' : '0');
  $('token-input').value = '';
  applyTokenState();
  toast(state.tokenWrites ? 'Token accepted: you can edit.' : 'Read token accepted: you can view this map, not edit it.');
  if (!state.mapId) start();
});
$('token-forget').addEventListener('click', forgetToken);

// ---------------------------------------------------------------- keys
document.addEventListener('keydown', (e) => {
  const t = e.target;
  if (t instanceof HTMLInputElement || t instanceof HTMLTextAreaElement || t instanceof HTMLSelectElement) return;
  if ($('save-dialog').open) return;
  const k = e.key.toLowerCase();
  const mod = e.ctrlKey || e.metaKey;
  if (mod && k === 'z') {
    e.preventDefault();
    if (!canEdit()) return;
    if (e.shiftKey) redo();
    else undo();
  } else if (mod && k === 'y') {
    e.preventDefault();
    if (canEdit()) redo();
  } else if (mod && k === 's') {
    e.preventDefault();
    openSave();
  } else if (mod || e.altKey) {
    // leave other shortcuts to the browser
  } else if (state.review && (k === 'a' || k === 'r' || e.key === ' ')) {
    e.preventDefault();
    reviewDecide(k === 'a' ? 'accepted' : k === 'r' ? 'rejected' : null);
  } else if (k === 'a' && state.selection.size) {
    setStatus(state.selection, 'accepted');
  } else if (k === 'r' && state.selection.size) {
    setStatus(state.selection, 'rejected');
  } else if ((e.key === 'Delete' || e.key === 'Backspace') && state.selection.size) {
    e.preventDefault();
    deleteMarkings(state.selection);
  } else if (k === 'n' && addListedMarking()) {
    // a listed missing marking was added as described
  } else if (k === 'n') {
    setMode('add');
  } else if (k === 'v') {
    setMode('select');
  } else if (e.key === 'Escape') {
    if (state.gesture) endGesture(null);
    else if (state.review) stopReview();
    else if (state.mode === 'add') setMode('select');
    else {
      state.selection.clear();
      render();
    }
  }
});

$('mode-select').addEventListener('click', () => setMode('select'));
$('mode-add').addEventListener('click', () => setMode('add'));

// ---------------------------------------------------------------- start
setMode('select');
applyTokenState();
function start() {
  return loadMaps().catch((err) => {
    const text = err instanceof ApiError && err.status === 401
      ? 'This server wants the API token even to read: enter it above.'
      : `The maps could not be loaded: ${problemText(err)}`;
    $('view-status').textContent = text;
    toast(text, 'error');
  });
}
start();

// For scripting and end-to-end tests: the map and the editor's state, read-only by convention.
globalThis.lanemapEditor = { map, state, layer, api, reviewPaging, follow, coverage: () => coverage };
