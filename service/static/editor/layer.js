// Markings drawn as oriented dashes on a Leaflet canvas: geometry and styles.

const L = globalThis.L;
const EARTH_RADIUS_M = 6378137;
const DEG = Math.PI / 180;

/** Detections scoring below this stand out (halo) so that a person looks at them first. */
export const LOW_SCORE = 0.5;
/** Length (m) drawn for a marking without one, so that it stays visible and clickable. */
const MIN_DRAWN_LENGTH_M = 0.4;

export const SOURCE_COLOURS = { detected: '#ffd60a', manual: '#2ee86f', imported: '#4cc9f0' };
export const REJECTED_COLOUR = '#ff4d4d';

/** Offset a lon/lat by east/north metres (local tangent plane; metres-scale accuracy is plenty). */
export function offset(lon, lat, east, north) {
  return [lon + (east / (EARTH_RADIUS_M * Math.cos(lat * DEG))) / DEG, lat + north / EARTH_RADIUS_M / DEG];
}

/** East/north metres from (lon0, lat0) to (lon1, lat1). */
export function metres(lon0, lat0, lon1, lat1) {
  return [(lon1 - lon0) * DEG * EARTH_RADIUS_M * Math.cos(((lat0 + lat1) / 2) * DEG), (lat1 - lat0) * DEG * EARTH_RADIUS_M];
}

/** The two ends [[lat, lon], [lat, lon]] of a marking's dash: bearing is clockwise from true north. */
export function dashEnds(m) {
  const half = Math.max(m.length_m || 0, MIN_DRAWN_LENGTH_M) / 2;
  const b = (m.bearing_deg || 0) * DEG;
  const [e, n] = [half * Math.sin(b), half * Math.cos(b)];
  const a = offset(m.lon, m.lat, -e, -n);
  const z = offset(m.lon, m.lat, e, n);
  return [[a[1], a[0]], [z[1], z[0]]];
}

/** A marking from its dash's two ends (lon/lat): centroid, length (m) and axis bearing in [0, 180). */
export function fromEnds(lonA, latA, lonB, latB) {
  const [e, n] = metres(lonA, latA, lonB, latB);
  const length = Math.hypot(e, n);
  let bearing = Math.atan2(e, n) / DEG;
  bearing = ((bearing % 180) + 180) % 180;
  return { lon: (lonA + lonB) / 2, lat: (latA + latB) / 2, length_m: length, bearing_deg: bearing };
}

/** The localizer's rule for doubted lengths (localizer/index.py: TYPICAL_CELL_M, TYPICAL_MIN, LENGTH_TOLERANCE, MAX_DASH_LENGTH_M). */
export const LENGTH_DOUBT = { cellM: 40, minCount: 6, tolerance: 0.15, maxLengthM: 8 };

/** The 40 m square of the page's own grid (east/north metres at the whole-degree latitude) a lon/lat lies in. */
export function lengthCell(lon, lat) {
  const lat0 = Math.floor(lat) * DEG;
  const east = lon * DEG * EARTH_RADIUS_M * Math.cos(lat0);
  const north = lat * DEG * EARTH_RADIUS_M;
  return `${Math.floor(east / LENGTH_DOUBT.cellM)},${Math.floor(north / LENGTH_DOUBT.cellM)}`;
}

function median(values) {
  const v = [...values].sort((a, b) => a - b);
  return (v[(v.length - 1) >> 1] + v[v.length >> 1]) / 2;
}

/**
 * The detections whose length the localizer doubts (localizer/index.py, length_slack): of
 * unknown kind, up to 8 m, their length departing from the median of such detections in
 * their 40 m square by more than 15 % + 0.1 m (the median of all of them where fewer than 6
 * lie in the square). They are matched with slack along their axis. The squares are the
 * page's own, not the map CRS's, so near a square's edge the page may judge a detection
 * against other neighbours than the server does. Returns a Map from id to the typical length (m).
 */
export function lengthDoubts(markings) {
  const cand = markings.filter((m) => m.source === 'detected' && m.status !== 'rejected'
    && !(m.kind && String(m.kind).trim()) && m.length_m > 0 && m.length_m <= LENGTH_DOUBT.maxLengthM);
  const out = new Map();
  if (cand.length < LENGTH_DOUBT.minCount + 1) return out;
  const cells = new Map();
  for (const m of cand) {
    const key = lengthCell(m.lon, m.lat);
    if (!cells.has(key)) cells.set(key, []);
    cells.get(key).push(m.length_m);
  }
  const all = median(cand.map((m) => m.length_m));
  const typical = new Map([...cells].map(([k, v]) => [k, v.length >= LENGTH_DOUBT.minCount ? median(v) : all]));
  for (const m of cand) {
    const t = typical.get(lengthCell(m.lon, m.lat));
    if (Math.abs(m.length_m - t) > LENGTH_DOUBT.tolerance * t + 0.1) out.set(String(m.id), t);
  }
  return out;
}

export function isLowScore(m) {
  return m.source === 'detected' && m.status === 'unreviewed' && m.score !== null && m.score < LOW_SCORE;
}

export function dashStyle(m) {
  const colour = m.status === 'rejected' ? REJECTED_COLOUR : SOURCE_COLOURS[m.source] || '#ffffff';
  return {
    color: colour,
    weight: m.status === 'accepted' ? 5 : m.status === 'rejected' ? 4 : 3,
    opacity: m.status === 'rejected' ? 0.9 : 1,
    dashArray: m.status === 'rejected' ? '5 4' : null,
    lineCap: 'butt',
  };
}

const HALOS = {
  conflict: { color: '#ff1f1f', weight: 14, opacity: 0.75, dashArray: '4 3' },
  selected: { color: '#ffffff', weight: 10, opacity: 0.95 },
  edited: { color: '#000000', weight: 8, opacity: 0.55 },
  low: { color: '#ff2bd6', weight: 10, opacity: 0.55 },
  length: { color: '#ff8c00', weight: 10, opacity: 0.6 },
};

/**
 * The layer of markings: one canvas polyline per marking, and halos beneath (selected,
 * conflicting, edited, low-score, doubtful length). Redraws only what changed.
 */
export class MarkingLayer {
  constructor(map, { onDown, onClick } = {}) {
    this.map = map;
    map.createPane('halos').style.zIndex = 390;
    map.createPane('dashes').style.zIndex = 400;
    this.haloRenderer = L.canvas({ pane: 'halos', padding: 0.3 });
    this.dashRenderer = L.canvas({ pane: 'dashes', padding: 0.3, tolerance: 6 });
    this.dashes = new Map(); // id -> {line, halo, sig}
    this.onDown = onDown;
    this.onClick = onClick;
  }

  /**
   * Draw exactly `markings`, with `flags(m)` naming its halo (or null).
   */
  draw(markings, flags) {
    const seen = new Set();
    for (const m of markings) {
      const id = String(m.id);
      seen.add(id);
      const halo = flags(m);
      const sig = [m.lon, m.lat, m.length_m, m.bearing_deg, m.source, m.status, halo].join('|');
      const old = this.dashes.get(id);
      if (old && old.sig === sig) continue;
      const ends = dashEnds(m);
      if (old) {
        old.line.setLatLngs(ends).setStyle(dashStyle(m));
        old.marking = m;
        if (old.halo) old.halo.remove();
        old.halo = halo ? L.polyline(ends, { ...HALOS[halo], renderer: this.haloRenderer, interactive: false, pane: 'halos' }).addTo(this.map) : null;
        old.sig = sig;
        continue;
      }
      const line = L.polyline(ends, { ...dashStyle(m), renderer: this.dashRenderer, pane: 'dashes', bubblingMouseEvents: false });
      const entry = { line, marking: m, sig, halo: null };
      line.on('mousedown', (e) => this.onDown?.(entry.marking, e));
      line.on('click', (e) => this.onClick?.(entry.marking, e));
      line.addTo(this.map);
      if (halo) entry.halo = L.polyline(ends, { ...HALOS[halo], renderer: this.haloRenderer, interactive: false, pane: 'halos' }).addTo(this.map);
      this.dashes.set(id, entry);
    }
    for (const [id, entry] of this.dashes) {
      if (seen.has(id)) continue;
      entry.line.remove();
      entry.halo?.remove();
      this.dashes.delete(id);
    }
  }

  /** Move one drawn dash while it is dragged (no edit yet). */
  preview(m) {
    const entry = this.dashes.get(String(m.id));
    if (!entry) return;
    const ends = dashEnds(m);
    entry.line.setLatLngs(ends);
    entry.halo?.setLatLngs(ends);
    entry.sig = null;
  }

  get size() {
    return this.dashes.size;
  }
}
