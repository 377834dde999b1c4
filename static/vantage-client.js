// Vantage client: keeps the items near a canvas's screen in a local Map, fed by the server.
//
// An ES module, no build step; import it from any page the server (or its CORS origins) allows:
//
//   import { VantageClient } from "https://vantage.example/static/vantage-client.js";
//   const client = new VantageClient({ url: "https://vantage.example", doc: "3f2a9c0b1d4e" });
//   client.onChange = (items) => redraw(items);           // a Map id -> item
//   await client.open();                                  // policy, document, stream
//   client.view([x0, y0, x1, y1], scale);                 // every frame (or every camera move)
//
// Transport: the WebSocket stream `/documents/{doc}/stream`; when it cannot open or closes (a
// proxy without WebSockets, a server restart, a network drop), diffs over HTTP with polling for
// edits, keeping the items held, while the stream is retried with backoff; back on the stream as
// soon as it opens. Only close codes 4404 (no such document), 4401 and 4403 (token) are final.
//
// Fetching: the screen plus an overscan margin, stretched towards where a moving screen will be;
// asked again only when the screen nears that margin's edge or the zoom changes the level of
// detail. The policy's numbers come from the server's /static/policy.json, which the simulator
// (app/simulate/policy.py) reads too, and so does its arithmetic: keep the two alike.

/**
 * @typedef {[number, number, number, number]} Rect  x0, y0, x1, y1 in canvas units, y downwards
 * @typedef {{count: number, cover: number}} Aggregate
 * @typedef {{x0: number, y0: number, cell: number, w: number, h: number, bits: string}} Mask
 *   the screen pixels an aggregate's members cover: `w` x `h` cells of `cell` canvas units from
 *   (x0, y0), one bit each, row by row, least significant bit first, base64
 * @typedef {{id: string, x0: number, y0: number, x1: number, y1: number, kind?: string, z?: number,
 *            data?: object, agg?: Aggregate, mask?: Mask}} Item  an aggregate has `agg` and an id
 *   starting "~"; zoomed out it has a `mask` too (see maskImage)
 * @typedef {object} Policy  static/policy.json's fields
 * @property {number} overscan    margin on each side, as a share of the screen
 * @property {number} refetchAt   ask again when the screen is closer than this share to the margin's edge
 * @property {number} lodStep     ask again when the zoom changed by more than this factor
 * @property {number} lookaheadS  also ask for where the screen will be this far ahead at its current speed
 * @property {number} smoothingS  the screen's velocity is smoothed over this many seconds
 * @property {number} minPx       items under this many pixels on screen are not shipped
 * @property {number} limit       items per answer
 * @property {number} pollMs      over HTTP, how often to ask for edits by others
 * @typedef {object} Status
 * @property {"ws" | "http" | "none"} transport  the stream, HTTP diffs and polling, or none (closed)
 * @property {boolean} live          the stream is open: edits by others arrive as they land
 * @property {boolean} reconnecting  the server cannot be reached: the items held stay, retrying
 * @property {number} rtt            the last answer's round trip, ms
 * @property {number} version        the document version the items held reflect
 * @property {string | null} error   what just went wrong, if something did
 * @typedef {{seq: number, rect: Rect, scale: number, at: number, band?: number | null}} Request
 */

/** Stream close codes after which retrying cannot help. */
const FINAL = new Map([
  [4404, "document not found"],
  [4401, "the stream needs a token"],
  [4403, "the token is not one this server accepts"],
]);
const RETRY_FIRST_MS = 250; // the stream is retried after 250 ms, then twice as long each time,
const RETRY_MOST_MS = 4000; // up to 4 s

const FIELDS = ["overscan", "refetchAt", "lodStep", "lookaheadS", "smoothingS", "minPx", "limit", "pollMs"];

/**
 * An aggregate's mask as an image: `mask.w` x `mask.h` pixels, those its members cover in
 * `colour` (a CSS colour), the rest clear. Made once per aggregate and colour, and kept on it.
 * Draw it over the mask's canvas rectangle, without smoothing, for the exact picture:
 *
 *   const m = item.mask, image = maskImage(item, "#ffd866");
 *   ctx.imageSmoothingEnabled = false;
 *   ctx.drawImage(image, (m.x0 - camX) * scale, (m.y0 - camY) * scale, m.w * m.cell * scale, m.h * m.cell * scale);
 *
 * @param {Item} item  an aggregate with a mask
 * @param {string} colour
 * @returns {HTMLCanvasElement | OffscreenCanvas}
 */
export function maskImage(item, colour) {
  const held = /** @type {any} */ (item)._maskImage;
  if (held && held.colour === colour) return held.image;
  const { w, h, bits } = /** @type {Mask} */ (item.mask);
  const image = typeof OffscreenCanvas === "function" ? new OffscreenCanvas(w, h) : Object.assign(document.createElement("canvas"), { width: w, height: h });
  const ctx = /** @type {CanvasRenderingContext2D} */ (image.getContext("2d"));
  ctx.fillStyle = colour;
  ctx.fillRect(0, 0, 1, 1);
  const [r, g, b] = ctx.getImageData(0, 0, 1, 1).data;  // the colour, as the canvas parses it
  const pixels = new ImageData(w, h);
  const packed = Uint8Array.from(atob(bits), (c) => c.charCodeAt(0));
  for (let i = 0; i < w * h; i++) {
    if (packed[i >> 3] & (1 << (i & 7))) pixels.data.set([r, g, b, 255], i * 4);
  }
  ctx.putImageData(pixels, 0, 0);
  /** @type {any} */ (item)._maskImage = { colour, image };
  return image;
}

/**
 * `rect` grown out to the pixel grid of `screen` at `scale`: its edges on the screen's pixel
 * edges, so the masks of the aggregates answered for it are drawn pixel for pixel, and stay
 * right as the screen pans by whole pixels. @returns {Rect}
 */
export function onPixels(/** @type {Rect} */ rect, /** @type {Rect} */ screen, /** @type {number} */ scale) {
  const [sx, sy] = screen;
  return [sx + Math.floor((rect[0] - sx) * scale) / scale, sy + Math.floor((rect[1] - sy) * scale) / scale,
          sx + Math.ceil((rect[2] - sx) * scale) / scale, sy + Math.ceil((rect[3] - sy) * scale) / scale];
}

/** `rect` grown by `share` of its size on each side (shrunk when negative). @returns {Rect} */
export function grown(/** @type {Rect} */ rect, /** @type {number} */ share) {
  const dx = (rect[2] - rect[0]) * share, dy = (rect[3] - rect[1]) * share;
  return [rect[0] - dx, rect[1] - dy, rect[2] + dx, rect[3] + dy];
}

/** Whether `inner` lies inside `outer`. */
export function inside(/** @type {Rect} */ inner, /** @type {Rect} */ outer) {
  return inner[0] >= outer[0] && inner[1] >= outer[1] && inner[2] <= outer[2] && inner[3] <= outer[3];
}

/** A non-2xx answer: `status` and the server's `detail`. */
export class VantageError extends Error {
  constructor(/** @type {number} */ status, /** @type {string} */ message) {
    super(message);
    this.status = status;
  }
}

const RENEW_MS = 60_000; // a token from a token function is renewed this long before it expires

/** Milliseconds until a JWT's `exp` (read, not verified: the server verifies); Infinity for a token
 * that is not a JWT. */
function expiresIn(/** @type {string} */ token) {
  try {
    const part = token.split(".")[1].replace(/-/g, "+").replace(/_/g, "/");
    const exp = JSON.parse(atob(part)).exp;
    return typeof exp === "number" ? exp * 1000 - Date.now() : Infinity;
  } catch {
    return Infinity;
  }
}

export class VantageClient extends EventTarget {
  /**
   * @param {object} [options]
   * @param {string} [options.url]     the server's base URL (default: this page's origin)
   * @param {string | null} [options.doc]    the document to open
   * @param {string | (() => string | Promise<string>) | null} [options.token]  a bearer token (sent in the
   *   stream's URL too: a browser cannot set its headers), or a function returning a fresh signed one,
   *   called again a minute before the last expires (the open stream is sent the fresh one)
   * @param {Partial<Policy> | null} [options.policy]  overrides of the server's /static/policy.json
   * @param {((items: Map<string, Item>) => void) | null} [options.onChange]  the items held changed
   * @param {((status: Status) => void) | null} [options.onStatus]  transport, round trip, version or an error
   */
  constructor({ url = globalThis.location ? location.origin : "", doc = null, token = null, policy = null,
                onChange = null, onStatus = null } = {}) {  // prettier-ignore
    super();
    this.url = url.replace(/\/+$/, "");
    this.doc = doc;
    this.tokenSource = token;
    /** @type {string | null} */ this.token = typeof token === "function" ? null : token;
    /** @type {any} */ this.renewTimer = null;
    /** @type {Policy | null} */
    this.policy = null; // loaded by ready()
    this.overrides = policy || {};
    this.onChange = onChange;
    this.onStatus = onStatus;
    /** @type {Map<string, Item>} what the server sent for `answered`, with edits since */
    this.items = new Map();
    this.version = 0;
    this.generation = 0; // bumped whenever `items` changes
    this.truncated = false;
    this.rtt = 0;
    this.lastDiff = 0; // entries that entered or left in the last change
    /** @type {"ws" | "http" | "none"} */
    this.transport = "ws";
    this.live = false;
    this.reconnecting = false;
    /** @type {Request | null} */ this.requested = null; // last asked for
    /** @type {Request | null} */ this.answered = null; // the request whose answer `items` reflects
    this.sent = 0;
    this.done = 0;
    /** @type {Rect | null} */ this.screen = null; // the screen as view() last had it
    this.scale = 1;
    this.velocity = { x: 0, y: 0 }; // units per second, smoothed: a fling is fetched ahead
    /** @type {{t: number, x: number, y: number, scale: number} | null} */ this.last = null;
    /** @type {Map<number, Request>} */ this.sentAt = new Map();
    /** @type {WebSocket | null} */ this.ws = null;
    this.busy = false; // an HTTP diff in flight
    this.epoch = 0; // bumped when the transport changes: an answer from before is dropped
    this.forcedHttp = false;
    this.backoff = 0;
    this.retryAt = 0;
    /** @type {any} */ this.pollTimer = null;
    /** @type {any} */ this.retryTimer = null;
  }

  // -- the server ------------------------------------------------------------------------

  /** fetch() against the server, with the token. */
  async request(/** @type {string} */ path, /** @type {RequestInit} */ init = {}) {
    const headers = new Headers(init.headers || {});
    const token = await this.currentToken();
    if (token) headers.set("Authorization", `Bearer ${token}`);
    return fetch(this.url + path, { ...init, headers });
  }

  /** The token to send: with a token function, a fresh one when the last is about to expire. */
  async currentToken() {
    if (typeof this.tokenSource !== "function") return this.token;
    if (!this.token || expiresIn(this.token) < RENEW_MS) {
      this.token = await this.tokenSource();
      this.renewBeforeExpiry();
    }
    return this.token;
  }

  /** Ask the token function for a fresh token a minute before this one expires, and send it on
   * the open stream, which the server would otherwise close (4401) at the expiry. */
  renewBeforeExpiry() {
    clearTimeout(this.renewTimer);
    const left = this.token ? expiresIn(this.token) : Infinity;
    if (!Number.isFinite(left)) return;
    this.renewTimer = setTimeout(async () => {
      try {
        this.token = await /** @type {() => string | Promise<string>} */ (this.tokenSource)();
        if (this.ws && this.ws.readyState === WebSocket.OPEN) this.ws.send(JSON.stringify({ token: this.token }));
        this.renewBeforeExpiry();
      } catch (error) {
        this.status(`could not renew the token: ${/** @type {any} */ (error).message || error}`);
      }
    }, Math.max(0, left - RENEW_MS));
  }

  /** The JSON answer of a request; a VantageError for a non-2xx one. @returns {Promise<any>} */
  async json(/** @type {string} */ path, /** @type {RequestInit} */ init = {}) {
    const response = await this.request(path, init);
    const body = await response.json().catch(() => null);
    if (!response.ok) {
      const detail = body && body.detail;
      throw new VantageError(response.status, typeof detail === "string" ? detail : response.statusText || `HTTP ${response.status}`);
    }
    return body;
  }

  docPath(/** @type {string} */ rest = "") {
    return `/documents/${encodeURIComponent(/** @type {string} */ (this.doc))}${rest}`;
  }

  /** Load the fetch policy (once): the server's /static/policy.json, with `policy`'s overrides. */
  async ready() {
    if (this.policy) return this.policy;
    let file = {};
    try {
      const response = await fetch(`${this.url}/static/policy.json`);
      if (response.ok) file = await response.json();
    } catch (error) {
      if (!FIELDS.every((f) => f in this.overrides)) throw error;
    }
    const policy = { ...file, ...this.overrides };
    const missing = FIELDS.filter((f) => typeof policy[f] !== "number");
    if (missing.length) throw new Error(`the policy lacks ${missing.join(", ")}`);
    this.policy = /** @type {Policy} */ (policy);
    return this.policy;
  }

  /** The documents: `[{id, name, version, items, bounds}, ...]`. */
  documents() {
    return this.json("/documents");
  }

  /** Open a document (the one given to the constructor by default): its metadata, once the
   * policy is loaded; the stream opens, and view() fetches. */
  async open(doc = this.doc) {
    await this.ready();
    if (!doc) throw new Error("no document to open");
    const meta = await this.json(`/documents/${encodeURIComponent(doc)}`);
    this.stop();
    Object.assign(this, { doc, version: meta.version, requested: null, answered: null, truncated: false,
                          transport: "ws", live: false, reconnecting: false, forcedHttp: false, backoff: 0,
                          retryAt: 0, busy: false });  // prettier-ignore
    this.epoch++;
    this.items.clear();
    this.sentAt.clear();
    this.changed();
    this.connect();
    return meta;
  }

  /** Close the stream and stop polling and retrying; the items held stay. */
  stop() {
    const ws = this.ws;
    this.ws = null;
    if (ws) ws.close();
    clearInterval(this.pollTimer);
    clearTimeout(this.retryTimer);
    this.pollTimer = this.retryTimer = null;
    this.live = false;
    this.epoch++;
    this.busy = false;
  }

  /** Close for good. */
  close() {
    this.stop();
    this.transport = "none";
    this.status();
  }

  /** One item by id, or null if the document has none by that id (or the id is invalid). */
  async item(/** @type {string} */ id) {
    try {
      return await this.json(this.docPath(`/items/${encodeURIComponent(id)}`));
    } catch (error) {
      if (error instanceof VantageError && (error.status === 404 || error.status === 422)) return null;
      throw error;
    }
  }

  /** Where the text holds `q` (a word or a phrase, which may run across items), in document
   * order, a page of hits: `{version, count, total, more, cursor, hits: [{ids, box, text}], items}`;
   * `next()` on a page that has `more` fetches the one after it. Options (or a number: the limit):
   * `limit` (20), `cursor`, `case: "match"`, `accents: "match"`, `whole: "words"`. */
  async search(/** @type {string} */ q, /** @type {any} */ options = {}) {
    const opts = typeof options === "number" ? { limit: options } : options;
    const params = new URLSearchParams({ q, limit: String(opts.limit ?? 20) });
    for (const key of ["cursor", "case", "accents", "whole"]) if (opts[key]) params.set(key, opts[key]);
    const page = await this.json(this.docPath(`/search?${params}`));
    if (page.more) page.next = () => this.search(q, { ...opts, cursor: page.cursor });
    return page;
  }

  /** The index's cells near `rect`: `{cells: [{box, depth, leaf}, ...]}`. */
  cells(/** @type {Rect} */ rect, limit = 3000) {
    return this.json(this.docPath(`/cells?x0=${rect[0]}&y0=${rect[1]}&x1=${rect[2]}&y1=${rect[3]}&limit=${limit}`));
  }

  // -- edits: the changes come back on the stream (or the next poll) like anyone's -------

  /** Create or replace an item: `{id, version}`. */
  put(/** @type {Item} */ item) {
    return this.json(this.docPath(`/items/${encodeURIComponent(item.id)}`), {
      method: "PUT", headers: { "Content-Type": "application/json" }, body: JSON.stringify(item),
    });
  }

  /** Change some fields of an item, keeping the rest (`data: null` drops its data). */
  patch(/** @type {string} */ id, /** @type {Partial<Item>} */ fields) {
    return this.json(this.docPath(`/items/${encodeURIComponent(id)}`), {
      method: "PATCH", headers: { "Content-Type": "application/json" }, body: JSON.stringify(fields),
    });
  }

  /** Delete one item by id, or many (an array), all or nothing. */
  delete(/** @type {string | string[]} */ ids) {
    if (Array.isArray(ids)) {
      return this.json(this.docPath("/items"), {
        method: "DELETE", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ ids }),
      });
    }
    return this.json(this.docPath(`/items/${encodeURIComponent(ids)}`), { method: "DELETE" });
  }

  /** Import items, all or nothing: an array of items, a JSON array's text, or NDJSON (text, a
   * Blob or a stream of bytes); `mode: "replace"` instead of what the document held.
   * @param {Item[] | string | Blob | ReadableStream} body
   * @returns {Promise<{imported: number, version: number}>} */
  import(body, { mode = "upsert" } = {}) {
    let type = "application/x-ndjson";
    if (Array.isArray(body)) {
      body = JSON.stringify(body);
      type = "application/json";
    } else if (typeof body === "string" && body.trimStart().startsWith("[")) {
      type = "application/json";
    }
    /** @type {any} */
    const init = { method: "POST", headers: { "Content-Type": type }, body };
    if (typeof ReadableStream !== "undefined" && body instanceof ReadableStream) init.duplex = "half";
    return this.json(this.docPath(`/items?mode=${mode}`), init);
  }

  // -- fetching what is near the screen ----------------------------------------------------

  /** Tell the client where the screen is (call it every frame, or whenever the camera moves):
   * it asks the server for more when the policy says so. */
  view(/** @type {Rect} */ screen, /** @type {number} */ scale, now = performance.now()) {
    this.screen = screen;
    this.scale = scale;
    this.track(now);
    if (this.needsRequest()) this.ask();
  }

  track(/** @type {number} */ now) {
    const { last, velocity } = this, x = this.screen[0], y = this.screen[1];
    if (last && now > last.t) {
      const dt = (now - last.t) / 1000, k = Math.min(1, dt / this.policy.smoothingS);
      velocity.x += k * ((x - last.x) / dt - velocity.x);
      velocity.y += k * ((y - last.y) / dt - velocity.y);
      if (this.scale !== last.scale) velocity.x = velocity.y = 0; // a zoom is not a fling
    }
    this.last = { t: now, x, y, scale: this.scale };
  }

  /** `rect` stretched towards where the screen is heading in `seconds`. @returns {Rect} */
  ahead(/** @type {Rect} */ rect, /** @type {number} */ seconds) {
    const dx = this.velocity.x * seconds, dy = this.velocity.y * seconds;
    return [rect[0] + Math.min(dx, 0), rect[1] + Math.min(dy, 0), rect[2] + Math.max(dx, 0), rect[3] + Math.max(dy, 0)];
  }

  /** Whether the screen (the last view() by default) needs a new request. */
  needsRequest(screen = this.screen, scale = this.scale) {
    const req = this.requested;
    if (!req || !screen) return true;
    const ratio = scale / req.scale;
    if (ratio > this.policy.lodStep || ratio < 1 / this.policy.lodStep) return true;
    const safe = grown(req.rect, -this.policy.refetchAt * this.policy.overscan / (1 + 2 * this.policy.overscan));
    return !inside(this.ahead(screen, this.policy.lookaheadS / 2), safe);
  }

  /** @returns {Request} */
  nextRequest() {
    const rect = onPixels(this.ahead(grown(this.screen, this.policy.overscan), this.policy.lookaheadS), this.screen, this.scale);
    return { seq: ++this.sent, rect, scale: this.scale, at: performance.now() };
  }

  /** The answer for the screen is in and nothing more is needed (for `screen`, by default the last view()'s). */
  synced(screen = this.screen, scale = this.scale) {
    return !!this.requested && this.done === this.requested.seq && !this.needsRequest(screen, scale) && !this.busy;
  }

  /** The zoom band of the aggregates held (null: real items only). */
  get band() {
    return this.answered ? this.answered.band ?? null : null;
  }

  ask() {
    if (!this.doc || !this.screen) return;
    if (this.transport === "ws") {
      const ws = this.ws;
      if (!ws || ws.readyState !== WebSocket.OPEN) return;
      const req = this.nextRequest();
      this.sentAt.set(req.seq, req);
      this.requested = req;
      ws.send(JSON.stringify({ seq: req.seq, viewport: req.rect, scale: req.scale, min_px: this.policy.minPx, limit: this.policy.limit }));
    } else if (this.transport === "http" && !this.busy && performance.now() >= this.retryAt) {
      const req = this.nextRequest();
      this.requested = req;
      this.fetchDiff(this.answered, req);
    }
  }

  // -- the items held ----------------------------------------------------------------------

  apply(answer) {
    if (answer.reset) this.items.clear();
    for (const id of answer.leave) this.items.delete(id);
    for (const item of answer.enter) this.items.set(item.id, item);
    this.version = answer.version;
    this.lastDiff = answer.enter.length + answer.leave.length;
    this.changed();
  }

  changed() {
    this.generation++;
    if (this.onChange) this.onChange(this.items);
    this.dispatchEvent(new CustomEvent("change", { detail: this.items }));
  }

  answer(/** @type {Request} */ request, answer) {
    this.apply(answer);
    request.band = answer.band; // the zoom band of its aggregates: a later diff starts from it
    this.answered = request;
    this.truncated = answer.truncated;
    this.done = request.seq;
    this.rtt = performance.now() - request.at;
    this.status();
  }

  /** @param {string | null} [error] */
  status(error = null) {
    /** @type {Status} */
    const s = { transport: this.transport, live: this.live, reconnecting: this.reconnecting, rtt: this.rtt,
                version: this.version, error };  // prettier-ignore
    if (this.onStatus) this.onStatus(s);
    this.dispatchEvent(new CustomEvent("status", { detail: s }));
  }

  // -- transports --------------------------------------------------------------------------

  connect() {
    clearTimeout(this.retryTimer);
    this.retryTimer = null;
    const query = this.token ? `?token=${encodeURIComponent(this.token)}` : "";
    const ws = new WebSocket(`${this.url.replace(/^http/, "ws")}${this.docPath("/stream")}${query}`);
    this.ws = ws;
    let opened = false;
    ws.onopen = () => {
      if (ws !== this.ws) return;
      opened = true;
      clearInterval(this.pollTimer);
      this.pollTimer = null;
      this.epoch++; // an HTTP answer still on its way is dropped: the stream starts afresh
      Object.assign(this, { transport: "ws", live: true, reconnecting: false, backoff: 0, busy: false,
                            requested: null, answered: null });  // prettier-ignore
      this.sentAt.clear(); // its first answer is a reset: the items held stay on screen until then
      this.status();
    };
    ws.onmessage = (event) => {
      if (ws !== this.ws) return;
      const msg = JSON.parse(event.data);
      if (msg.type === "error") return this.status(msg.message);
      if (msg.type === "edit") {
        this.apply(msg);
        return this.status();
      }
      const req = this.sentAt.get(msg.seq);
      for (const seq of this.sentAt.keys()) if (seq <= msg.seq) this.sentAt.delete(seq); // superseded ones too
      if (req) this.answer(req, msg);
    };
    ws.onclose = (event) => {
      if (ws !== this.ws) return;
      this.ws = null;
      this.live = false;
      if (FINAL.has(event.code)) {
        this.stop();
        this.transport = "none";
        return this.status(event.reason || FINAL.get(event.code));
      }
      // No stream (a proxy without WebSockets, a restart, a dropped network): the items held
      // stay, HTTP diffs and polling meanwhile, and the stream is tried again.
      if (opened) this.reconnecting = true; // it was open: the server went away, or the network
      if (this.transport !== "http") this.fallBack();
      else this.status();
      this.retryLater();
    };
  }

  retryLater() {
    if (this.forcedHttp || this.retryTimer) return;
    const delay = Math.min(RETRY_MOST_MS, RETRY_FIRST_MS * 2 ** this.backoff++);
    this.retryTimer = setTimeout(() => this.connect(), delay * (0.75 + 0.5 * Math.random()));
  }

  fallBack() {
    this.transport = "http";
    this.epoch++;
    this.busy = false;
    this.requested = this.answered;
    clearInterval(this.pollTimer);
    this.pollTimer = setInterval(() => this.poll(), this.policy.pollMs);
    this.status();
  }

  /** Diffs over HTTP from now on, and polling for edits; no stream is tried again. */
  useHttp() {
    const ws = this.ws;
    this.ws = null;
    if (ws) ws.close();
    clearTimeout(this.retryTimer);
    this.retryTimer = null;
    this.forcedHttp = true;
    this.live = false;
    this.fallBack();
  }

  poll() {
    if (this.busy || !this.screen) return;
    if (!this.answered || this.needsRequest()) return this.ask(); // (a view() the app has not repeated)
    // The same view again: only edits since our version come back.
    this.requested = { ...this.answered, seq: ++this.sent, at: performance.now() };
    this.fetchDiff(this.answered, this.requested);
  }

  async fetchDiff(/** @type {Request | null} */ from, /** @type {Request} */ to) {
    this.busy = true;
    const doc = this.doc, epoch = this.epoch, policy = this.policy;
    const common = `scale=${to.scale}&min_px=${policy.minPx}&limit=${policy.limit}`;
    const path = from
      ? this.docPath(`/diff?from=${from.rect.join(",")}&to=${to.rect.join(",")}&from_scale=${from.scale}&${common}`) +
        `&since=${this.version}${from.band == null ? "" : `&from_band=${from.band}`}`
      : this.docPath(`/viewport?x0=${to.rect[0]}&y0=${to.rect[1]}&x1=${to.rect[2]}&y1=${to.rect[3]}&${common}`);
    try {
      const body = await this.json(path);
      if (doc !== this.doc || epoch !== this.epoch) return;
      if (!from) Object.assign(body, { reset: true, leave: [], enter: body.items });
      this.reconnecting = false;
      this.answer(to, body);
    } catch (error) {
      if (doc !== this.doc || epoch !== this.epoch) return;
      // Keep the items held; ask again after a poll's wait.
      this.requested = this.answered;
      this.retryAt = performance.now() + policy.pollMs;
      const unreachable = !(error instanceof VantageError) || error.status >= 500;
      this.reconnecting = unreachable;
      this.status(unreachable ? "the server cannot be reached: reconnecting" : String(error.message || error));
      if (unreachable) this.retryLater();
    } finally {
      if (epoch === this.epoch) this.busy = false;
    }
  }
}
