// Local edits of one map: what changed since the last save, undo/redo, persistence,
// and the changeset that saves them. No DOM, no network.
//
// A marking is a flat object {id, lon, lat, weight, length_m, width_m, bearing_deg,
// score, kind, source, status, version}. `pending` maps an id to {base, cur}: base is
// the server's marking the edit started from (null for a new one), cur the marking
// as edited (null once deleted). An undo record lists, per id, the pending entry
// before and after the command (undefined: no pending edit).

export const EDITABLE = ['lon', 'lat', 'weight', 'length_m', 'width_m', 'bearing_deg', 'kind', 'status'];
const PROPS = ['weight', 'length_m', 'width_m', 'bearing_deg', 'score', 'kind', 'source', 'status'];
const MAX_UNDO = 500;

export function isLocalId(id) {
  return typeof id === 'string' && id.startsWith('new-');
}

function sameValue(a, b) {
  if (typeof a === 'number' && typeof b === 'number') return Math.abs(a - b) < 1e-9;
  return a === b;
}

/** Names of the fields in which `b` differs from `a` (the ones saved). */
export function changedFields(a, b) {
  return EDITABLE.filter((k) => !sameValue(a[k], b[k]));
}

function clone(x) {
  return x === undefined ? undefined : JSON.parse(JSON.stringify(x));
}

/** `cur` re-applied onto a newer server version `base2` of the marking it was edited from. */
export function rebaseEntry(entry, base2) {
  if (!entry) return entry;
  if (entry.cur === null) return { base: clone(base2), cur: null };
  const cur = { ...clone(base2) };
  for (const k of changedFields(entry.base, entry.cur)) cur[k] = entry.cur[k];
  return { base: clone(base2), cur };
}

export class EditSession {
  /**
   * @param {string} key  localStorage key of this map's unsaved edits
   * @param {Storage|null} storage  where they survive a reload (null: nowhere)
   */
  constructor(key, storage = globalThis.localStorage ?? null) {
    this.key = key;
    this.storage = storage;
    this.pending = new Map();
    this.undoStack = [];
    this.redoStack = [];
    this.nextLocal = 1;
    this.persistFailed = false;
    this.listeners = new Set();
    this.restored = this.load();
  }

  onChange(fn) {
    this.listeners.add(fn);
  }

  notify() {
    this.persist();
    for (const fn of this.listeners) fn(this);
  }

  get count() {
    return this.pending.size;
  }

  /** The marking as edited locally: the server's `server` unless changed; null when deleted. */
  effective(id, server) {
    const e = this.pending.get(String(id));
    if (!e) return server ?? null;
    return e.cur;
  }

  /** New markings and edited ones, as they are locally (deleted ones left out). */
  localMarkings() {
    return [...this.pending.values()].filter((e) => e.cur !== null).map((e) => e.cur);
  }

  newLocalId() {
    return `new-${this.nextLocal++}`;
  }

  /**
   * Apply one command: `changes` is a list of {base, cur} where base is the server marking
   * (null for a new one) and cur the marking after the command (null: deleted).
   */
  apply(label, changes) {
    const record = { label, items: [] };
    for (const { base, cur } of changes) {
      const id = String((cur ?? base).id);
      const before = clone(this.pending.get(id));
      const origin = before ? before.base : clone(base);
      let after = { base: origin, cur: clone(cur) };
      if (origin === null && cur === null) after = undefined; // a new marking deleted again
      else if (origin !== null && cur !== null && changedFields(origin, cur).length === 0) after = undefined;
      if (JSON.stringify(before) === JSON.stringify(after)) continue;
      this.setEntry(id, after);
      record.items.push({ id, before, after: clone(after) });
    }
    if (!record.items.length) return false;
    this.undoStack.push(record);
    if (this.undoStack.length > MAX_UNDO) this.undoStack.shift();
    this.redoStack = [];
    this.notify();
    return true;
  }

  setEntry(id, entry) {
    if (entry === undefined) this.pending.delete(id);
    else this.pending.set(id, clone(entry));
  }

  /** Undo the last command; returns its record (null when there is none). */
  undo() {
    const record = this.undoStack.pop();
    if (!record) return null;
    for (const it of [...record.items].reverse()) this.setEntry(it.id, it.before);
    this.redoStack.push(record);
    this.notify();
    return record;
  }

  redo() {
    const record = this.redoStack.pop();
    if (!record) return null;
    for (const it of record.items) this.setEntry(it.id, it.after);
    this.undoStack.push(record);
    this.notify();
    return record;
  }

  /** Forget every unsaved edit (after a save, or when the person discards them). */
  clear() {
    this.pending.clear();
    this.undoStack = [];
    this.redoStack = [];
    this.notify();
  }

  /**
   * Re-apply the edits of the given markings onto their current server versions.
   * `current` maps id -> the server's marking now, or null where it no longer exists;
   * edits of markings that no longer exist are dropped. Returns the dropped ids.
   */
  rebase(current) {
    const dropped = [];
    const fix = (id, entry) => {
      if (!entry || !current.has(id)) return entry;
      const now = current.get(id);
      return now === null ? undefined : rebaseEntry(entry, now);
    };
    for (const [id, entry] of [...this.pending]) {
      if (!current.has(id)) continue;
      if (current.get(id) === null) dropped.push(id);
      this.setEntry(id, fix(id, entry));
    }
    for (const stack of [this.undoStack, this.redoStack]) {
      for (const rec of stack) {
        for (const it of rec.items) {
          it.before = fix(it.id, it.before);
          it.after = fix(it.id, it.after);
        }
      }
    }
    this.notify();
    return dropped;
  }

  /** The changeset request body saving every pending edit, and the ids in its order. */
  toChangeset(comment) {
    const changes = [];
    const ids = [];
    for (const [id, { base, cur }] of this.pending) {
      if (base === null) {
        changes.push({ op: 'create', feature: toFeature(cur) });
      } else if (cur === null) {
        changes.push({ op: 'delete', id, version: base.version });
      } else {
        const patch = {};
        const fields = changedFields(base, cur);
        if (fields.includes('lon') || fields.includes('lat')) {
          patch.geometry = { type: 'Point', coordinates: [cur.lon, cur.lat] };
        }
        const props = fields.filter((k) => k !== 'lon' && k !== 'lat');
        if (props.length) patch.properties = Object.fromEntries(props.map((k) => [k, cur[k]]));
        changes.push({ op: 'update', id, version: base.version, patch });
      }
      ids.push(id);
    }
    return { body: { comment, changes }, ids };
  }

  /** Keep the edits in storage; `persistFailed` tells when even the edits alone did not fit. */
  persist() {
    if (!this.storage) return;
    if (!this.pending.size && !this.undoStack.length && !this.redoStack.length) {
      this.storage.removeItem(this.key);
      this.persistFailed = false;
      return;
    }
    const data = { v: 1, savedAt: new Date().toISOString(), pending: [...this.pending], nextLocal: this.nextLocal };
    try {
      this.storage.setItem(this.key, JSON.stringify({ ...data, undo: this.undoStack, redo: this.redoStack }));
      this.persistFailed = false;
    } catch {
      try {
        this.storage.setItem(this.key, JSON.stringify({ ...data, undo: [], redo: [] })); // the edits matter most
        this.persistFailed = false;
      } catch (err) {
        console.warn('unsaved edits could not be kept in localStorage', err);
        this.persistFailed = true;
      }
    }
  }

  /** Restore what an earlier page left unsaved; returns how many markings it had changed. */
  load() {
    if (!this.storage) return 0;
    let data;
    try {
      data = JSON.parse(this.storage.getItem(this.key) || 'null');
    } catch {
      data = null;
    }
    if (!data || data.v !== 1) return 0;
    this.pending = new Map(data.pending);
    this.undoStack = data.undo || [];
    this.redoStack = data.redo || [];
    this.nextLocal = data.nextLocal || 1;
    return this.pending.size;
  }
}

/** A marking from a GeoJSON feature of the API. */
export function fromFeature(f) {
  const p = f.properties || {};
  const m = { id: String(f.id), lon: f.geometry.coordinates[0], lat: f.geometry.coordinates[1] };
  for (const k of PROPS) m[k] = p[k] ?? null;
  m.version = p.version == null ? null : String(p.version);
  return m;
}

/** A GeoJSON feature to create a marking (ids and versions are the server's to give). */
export function toFeature(m) {
  const properties = {};
  for (const k of PROPS) if (m[k] !== null && m[k] !== undefined) properties[k] = m[k];
  return { type: 'Feature', geometry: { type: 'Point', coordinates: [m.lon, m.lat] }, properties };
}
