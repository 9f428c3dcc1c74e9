// The service's public HTTP API, as the editor uses it. Errors are RFC 9457 problems.

import { fromFeature } from './edits.js';

export class ApiError extends Error {
  /** @param {string|null} requestId  the answer's X-Request-ID, which the server's log shows */
  constructor(status, problem, requestId = null) {
    super(problem?.detail || problem?.title || `HTTP ${status}`);
    this.status = status;
    this.problem = problem || {};
    this.requestId = requestId;
  }
}

export class Api {
  /**
   * @param {URL|string} root  the service's root URL (the editor lives at root + "editor/")
   * @param {() => string|null} token  the bearer token for writes, when there is one
   */
  constructor(root, token) {
    this.root = new URL(root);
    this.token = token;
  }

  url(path) {
    return new URL(path.replace(/^\//, ''), this.root);
  }

  /** The headers every request sends: the token too when there is one (a server may want it for reads). */
  headers(token) {
    const headers = { Accept: 'application/json, application/geo+json, application/problem+json' };
    const bearer = token ?? this.token();
    if (bearer) headers.Authorization = `Bearer ${bearer}`;
    return headers;
  }

  async request(method, path, { body, signal, token } = {}) {
    const headers = this.headers(token);
    if (body !== undefined) headers['Content-Type'] = 'application/json';
    const url = path instanceof URL ? path : this.url(path);
    const res = await fetch(url, { method, headers, body: body === undefined ? undefined : JSON.stringify(body), signal });
    const text = await res.text();
    let data = null;
    try {
      data = text ? JSON.parse(text) : null;
    } catch {
      data = { detail: text.slice(0, 200) };
    }
    if (!res.ok) throw new ApiError(res.status, data, res.headers.get('X-Request-ID'));
    return data;
  }

  collections() {
    return this.request('GET', 'collections').then((d) => d.collections);
  }

  collection(mapId) {
    return this.request('GET', `collections/${encodeURIComponent(mapId)}`);
  }

  /** The ground the map speaks for, as localization draws it: a GeoJSON Feature (WGS84). */
  coverage(mapId) {
    return this.request('GET', `collections/${encodeURIComponent(mapId)}/coverage`);
  }

  /** The map's markings counted by status, source and kind, and how far its review has come. */
  summary(mapId, bbox = null) {
    const q = bbox ? `?bbox=${bbox.map((v) => v.toFixed(7)).join(',')}` : '';
    return this.request('GET', `collections/${encodeURIComponent(mapId)}/summary${q}`);
  }

  imagery(mapId) {
    return this.request('GET', `collections/${encodeURIComponent(mapId)}/imagery`).then((d) => d.imagery);
  }

  tileUrl(mapId) {
    return `${this.url(`collections/${encodeURIComponent(mapId)}/imagery/tiles/WebMercatorQuad`)}/{z}/{x}/{y}.png`;
  }

  /**
   * Every marking in a box (following the `next` links), as flat markings.
   * @param {number[]|null} bbox  [west, south, east, north] in degrees; null: the whole map
   */
  async items(mapId, bbox, { status, signal, pageSize = 5000, onPage } = {}) {
    const q = new URLSearchParams({ limit: String(pageSize) });
    if (bbox) q.set('bbox', bbox.map((v) => v.toFixed(7)).join(','));
    if (status) q.set('status', status);
    let url = this.url(`collections/${encodeURIComponent(mapId)}/items?${q}`);
    const out = [];
    while (url) {
      const page = await this.request('GET', url, { signal });
      for (const f of page.features) out.push(fromFeature(f));
      onPage?.(out.length, page.numberMatched);
      const next = (page.links || []).find((l) => l.rel === 'next');
      url = next ? new URL(next.href) : null;
    }
    return out;
  }

  /**
   * A page of the map's review queue (its unreviewed detections, lowest score first; within
   * `bbox` when given), from its start or from the `next` URL of the page before
   * (or of `reviewQueueUrl`):
   * {items, total (the whole queue's length), next (null after the last page)}.
   */
  async reviewQueue(mapId, bbox, { next = null, pageSize = 500, signal } = {}) {
    const url = next ?? this.reviewQueueUrl(mapId, bbox, { pageSize });
    const page = await this.request('GET', url, { signal });
    const link = (page.links || []).find((l) => l.rel === 'next');
    return { items: page.features.map(fromFeature), total: page.numberMatched, next: link ? new URL(link.href) : null };
  }

  /** The review queue's page of `pageSize` from its start, or after a detection of it (`after`: {score, id}). */
  reviewQueueUrl(mapId, bbox, { after = null, pageSize = 500 } = {}) {
    const q = new URLSearchParams({ limit: String(pageSize) });
    if (bbox) q.set('bbox', bbox.map((v) => v.toFixed(7)).join(','));
    if (after) q.set('after', `${after.score ?? 'none'},${after.id}`);
    return this.url(`collections/${encodeURIComponent(mapId)}/review/queue?${q}`);
  }

  /**
   * What changed in the map since `revision` (following the `next` links): the revision
   * the map is now at, and each changed marking's id with its state now (null: deleted).
   * With `max`, more changes than that are not read: `now` is then null, and `count` says
   * how many there are.
   */
  async changes(mapId, revision, { signal, max = null } = {}) {
    const q = new URLSearchParams({ since: String(revision) });
    if (max) q.set('limit', String(max));
    let url = this.url(`collections/${encodeURIComponent(mapId)}/changes?${q}`);
    const now = new Map();
    let at = revision;
    while (url) {
      const page = await this.request('GET', url, { signal });
      if (max && page.numberMatched > max) return { revision: page.revision, now: null, count: page.numberMatched };
      for (const r of page.removed) now.set(String(r.id), null);
      for (const f of page.features) now.set(String(f.id), fromFeature(f));
      at = page.revision;
      const next = (page.links || []).find((l) => l.rel === 'next');
      url = next ? new URL(next.href) : null;
    }
    return { revision: at, now };
  }

  /** The server's marking now, or null when it no longer exists. */
  async item(mapId, id) {
    try {
      const f = await this.request('GET', `collections/${encodeURIComponent(mapId)}/items/${encodeURIComponent(id)}`);
      return fromFeature(f);
    } catch (err) {
      if (err instanceof ApiError && err.status === 404) return null;
      throw err;
    }
  }

  /** The map as saved, scored against true markings (a GeoJSON FeatureCollection). */
  evaluate(mapId, truth) {
    return this.request('POST', `collections/${encodeURIComponent(mapId)}/evaluate`, { body: truth });
  }

  saveChangeset(mapId, body) {
    return this.request('POST', `collections/${encodeURIComponent(mapId)}/changesets`, { body });
  }

  changesets(mapId, { limit = 30, offset = 0 } = {}) {
    return this.request('GET', `collections/${encodeURIComponent(mapId)}/changesets?limit=${limit}&offset=${offset}`);
  }

  changeset(mapId, id) {
    return this.request('GET', `collections/${encodeURIComponent(mapId)}/changesets/${encodeURIComponent(id)}`);
  }

  /** Accept and reject unreviewed detections by score, one changeset (`dry_run`: only count). */
  reviewByScore(mapId, body) {
    return this.request('POST', `collections/${encodeURIComponent(mapId)}/review`, { body });
  }

  revert(mapId, id, comment) {
    return this.request('POST', `collections/${encodeURIComponent(mapId)}/changesets/${encodeURIComponent(id)}/revert`,
      { body: { comment } });
  }

  /**
   * What the server lets `token` do, without writing anything: `'write'`, `'read'` (a read
   * token, `LANEMAP_READ_TOKENS`) or `null` (unknown to the server). A map without an id is
   * refused as unauthorized (401) or forbidden (403) before it is refused as invalid (422).
   */
  async checkToken(token) {
    try {
      await this.request('POST', 'collections', { body: {}, token });
    } catch (err) {
      if (err instanceof ApiError && err.status === 401) return null;
      if (err instanceof ApiError && err.status === 403) return 'read';
      if (err instanceof ApiError && err.status === 422) return 'write';
      throw err;
    }
    throw new Error('the server accepted a map without an id');
  }
}
