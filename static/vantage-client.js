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
//
// Tiles (`tiles: true`): zoomed out (the view shows many aggregates: TILED_LEAST, TILED_SHARE),
// the aggregates do not come in answers but in tiles fixed in canvas space, fetched once and
// kept across pans and zooms (and by the browser's cache: a tile's URL names the version of the
// answer that named it, and never changes). Tiled answers come over HTTP (the stream sends
// aggregates inline), so zoomed out the client asks by HTTP diffs and polls for edits; zoomed in
// again, it opens the stream again. A tile's bits are pixels of a *ladder* scale,
// `ladderScale(z)`: drawn at that scale, with the view's corner on a multiple of its pixel
// (`onLadder`), each bit is one screen pixel. Of the tiles an answer names (the rect asked for,
// stretched ahead of a fast move), only those touching the screen and its overscan margin are
// fetched and kept, a few at a time, nearest the screen first; a pan fetches those entering the
// margin. A first view that looks zoomed out (`crowded`) is asked tiled from the start.
//
//   const client = new VantageClient({ url, doc, tiles: true }), painter = new TilePainter();
//   painter.frame();                                      // every frame, before drawing
//   for (const { kind } of client.layerOrder())           // lowest z first
//     for (const tile of client.tiles())                  // those held of the answer's, near the screen
//       painter.draw(ctx, tile, kind, colours[kind], camX, camY, scale);
//   client.tileAggregates()                               // their aggregates, as items: `boxed`
//                                                         // ones have no bits: draw their box

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
 * @typedef {object} Sheet  the tiles a tiled answer names (its `tiles`), and its version
 * @property {number} band
 * @property {number} z        the tiles' ladder level: `ladderScale(z)` pixels a unit
 * @property {number} size     pixels along a tile's side
 * @property {[number, number, number, number]} range  tx0, ty0, tx1, ty1, inclusive
 * @property {number} version  the answer's: the tiles' URLs name it
 * @typedef {object} TileColumns  a tile's aggregates, a column a field (as served)
 * @property {number[]} index  the id is `~{band}.{index}`
 * @property {number[]} box    c0, r0, c1, r1 an aggregate, in the tile's pixels from its corner
 * @property {number[]} count
 * @property {number[]} cover  thousandths
 * @property {string[]} kind
 * @property {number[]} z
 * @property {number[]} boxed  positions of the aggregates without bits: drawn as their box
 * @typedef {object} Tile  a tile, decoded
 * @property {string} path     its URL's path and query (the cache's key)
 * @property {string | null} etag
 * @property {number} band
 * @property {number} z
 * @property {number} tx
 * @property {number} ty
 * @property {number} scale    its pixels a canvas unit: `ladderScale(z)`
 * @property {Rect} box        canvas units: pixels `tx * size` to `(tx + 1) * size` of its scale
 * @property {number} size     pixels along its side
 * @property {TileColumns} aggregates
 * @property {Map<string, Uint8Array>} layers  kind -> `size` rows of `size` bits from the
 *   tile's top-left corner, least significant bit first: a set bit is a pixel a member of an
 *   aggregate of that kind touches
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

// Zoomed out, for tiles: the view shows at least this many aggregates, and at least this share of
// as many as items; zoomed in again under half of each (a few aggregates cost an answer little,
// and the stream's live edits are worth more).
const TILED_LEAST = 32;
const TILED_SHARE = 0.25;
const TILE_MOST = 256;  // tiles held, the least recently named dropped first (never those near the screen)
const TILE_LOADS = 6;  // tiles fetched at once (what a browser sends at once to one HTTP/1.1 origin)
// Before any answer, a view looks zoomed out when the document's items, spread evenly over its
// bounds, would have under this many square pixels of screen each (a 5.7 x 5.7 pixel square).
const ROOM_PX = 32;
const IMAGE_MOST = 16 << 20;  // pixels of tile images a TilePainter keeps, the least recently drawn dropped
const RENDER_MS = 8;  // a frame makes new tile images for this long, then stretches older ones until the next
const PHASE_STEPS = 1e6;  // a tile's offset within a pixel, to this fraction of one, keys its images
const SCALED_PAST = 2048;  // a tile wider on screen than this many pixels: its bits drawn as scaled pixels
const LITTLE_ENDIAN = new Uint8Array(new Uint32Array([1]).buffer)[0] === 1;
const EDGE = 1e-7;  // a bit overlapping a pixel by less than this share of it does not ink it (float noise)
const LADDER_STEPS = 4;  // ladder scales an octave
// 2**(-k/4), written as the server's floats are (Math.pow rounds two of them the other way)
const ROOTS = [1, 0.8408964152537145, 0.7071067811865476, 0.5946035575013605];

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

/** Pixels a unit at ladder level `z`: `2**(-z/4)`, the very float the server's tiles are made at. */
export function ladderScale(/** @type {number} */ z) {
  return ROOTS[((z % LADDER_STEPS) + LADDER_STEPS) % LADDER_STEPS] * 2 ** -Math.floor(z / LADDER_STEPS);
}

/** The ladder level nearest `scale` (its own, when `scale` is on the ladder). */
export function ladderLevel(/** @type {number} */ scale) {
  return Math.round(-LADDER_STEPS * Math.log2(scale));
}

/** `view` (its top-left canvas point, pixels a unit) at the largest ladder scale not above its
 * own (what fits at `view.scale` fits there; what it shows zoomed out, it shows there too), the
 * canvas point at pixel `anchor` staying there (to within half a pixel), its corner on a multiple
 * of a pixel: tiles drawn there fall on its pixels, bit for pixel.
 * @param {{x: number, y: number, scale: number}} view
 * @param {[number, number]} anchor  a pixel of the screen: the last zoom's, or its centre
 * @returns {{x: number, y: number, scale: number}} */
export function onLadder(view, anchor) {
  const scale = ladderScale(Math.ceil(-LADDER_STEPS * Math.log2(view.scale) - 1e-9));  // a scale on it: itself
  const [ax, ay] = anchor, ux = view.x + ax / view.scale, uy = view.y + ay / view.scale;
  return { x: Math.round((ux - ax / scale) * scale) / scale, y: Math.round((uy - ay / scale) * scale) / scale, scale };
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
   * @param {boolean} [options.tiles]  zoomed out, take the aggregates from tiles (`tiles()`) instead of
   *   answers: the items held are then only those drawn themselves
   */
  constructor({ url = globalThis.location ? location.origin : "", doc = null, token = null, policy = null,
                onChange = null, onStatus = null, tiles = false } = {}) {  // prettier-ignore
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
    this.generation = 0; // bumped whenever `items`, or the tiles held of the answer's, change
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
    this.tiled = tiles;
    this.zoomedOut = false; // the view shows many aggregates: tiled, views go over HTTP
    this.aggregatesHeld = 0; // of `items`
    /** @type {Sheet | null} */ this.sheet = null; // the tiles the answer held names
    /** @type {[number, number, number, number] | null} */
    this.tileRange = null; // those of them near the screen (tx0, ty0, tx1, ty1, inclusive): fetched, drawn
    /** @type {Set<string>} */ this.named = new Set(); // their paths
    /** @type {{items: number, bounds: Rect | null} | null} */ this.meta = null; // the open document's
    this.opening = false; // open, its first view not seen yet (tiled: the transport waits for it)
    /** @type {Map<string, Tile>} */ this.tileCache = new Map(); // by path, least recently named first
    /** @type {Map<string, string>} */ this.tileAt = new Map(); // a tile's path without its version -> the newest held
    /** @type {Map<string, AbortController>} */ this.tileLoads = new Map(); // in flight, by path
    /** @type {Map<string, number>} */ this.tileRetry = new Map(); // failed: not asked again before then
    this.tileFetches = 0; // tile requests made
    /** @type {{of: number, tiles: Tile[]}} */ this.tileList = { of: -1, tiles: [] };
    /** @type {{tiles: Tile[] | null, items: Item[]}} */ this.tileItems = { tiles: null, items: [] };
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
   * policy is loaded; the stream opens, and view() fetches. With `tiles: true`, the transport
   * waits for the first view (`firstView`): one that looks zoomed out is asked over HTTP, tiled. */
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
    this.aggregatesHeld = 0;
    this.sentAt.clear();
    this.setSheet(null);
    this.zoomedOut = false;
    this.meta = { items: meta.items, bounds: meta.bounds };
    this.changed();
    if (this.tiled) this.opening = true;
    else this.connect();
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
    this.opening = false;
    this.epoch++;
    this.busy = false;
    for (const control of this.tileLoads.values()) control.abort();
    this.tileLoads.clear();
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
   * order, a page of hits: `{version, count, total, more, cursor, hits: [{ids, box, boxes, text}], items}`
   * (a hit's `boxes`: one a line it covers; `box`: their union);
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
    if (this.opening) this.firstView(screen, scale);
    this.track(now);
    if (this.needsRequest()) this.ask();
    if (this.sheet && this.aimTiles()) this.fetchTiles(); // tiles entering the margin
  }

  /** Where the screen first is after open(), for an app that knows it before its first view()
   * (which calls this itself otherwise). With `tiles: true`, a first view that looks zoomed out
   * (`crowded`) is asked tiled over HTTP from the start, not answered aggregates and their masks
   * on the stream first; any other opens the stream. */
  firstView(/** @type {Rect} */ screen, /** @type {number} */ scale) {
    if (!this.opening) return;
    this.opening = false;
    if (!this.crowded(screen, scale)) return this.connect();
    this.zoomedOut = true;
    this.generation++;
    this.fallBack();
  }

  /** Whether `screen` at `scale` looks zoomed out, from the open document's item count and
   * bounds alone (before any answer says): its items, spread evenly over its bounds (grown by
   * half a pixel each side: a flat document is a pixel thick), would have under ROOM_PX square
   * pixels of screen each, and at least TILED_LEAST of them lie on the screen. */
  crowded(/** @type {Rect} */ screen, /** @type {number} */ scale) {
    const n = this.meta ? this.meta.items : 0, b = this.meta && this.meta.bounds, pad = 0.5 / scale;
    if (!n || !b || !(scale > 0)) return false;
    const box = [b[0] - pad, b[1] - pad, b[2] + pad, b[3] + pad];
    const w = box[2] - box[0], h = box[3] - box[1];
    const seenW = Math.max(0, Math.min(box[2], screen[2]) - Math.max(box[0], screen[0]));
    const seenH = Math.max(0, Math.min(box[3], screen[3]) - Math.max(box[1], screen[1]));
    return (w * scale * h * scale) / n < ROOM_PX && (n * seenW * seenH) / (w * h) >= TILED_LEAST;
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
    // Tiled, the tiles are of the ladder level nearest the scale: another level, other tiles.
    if (this.sheet && ladderLevel(scale) !== ladderLevel(req.scale)) return true;
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
    return !!this.requested && this.done === this.requested.seq && !this.needsRequest(screen, scale) && !this.busy &&
      !this.tileLoads.size;
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
    const items = this.items;
    if (answer.reset) {
      items.clear();
      this.aggregatesHeld = 0;
    }
    for (const id of answer.leave) if (items.delete(id) && id.startsWith("~")) this.aggregatesHeld--;
    for (const item of answer.enter) {
      if (item.id.startsWith("~") && !items.has(item.id)) this.aggregatesHeld++;
      items.set(item.id, item);
    }
    if (answer.tiles !== undefined && this.aggregatesHeld) {  // tiled: no aggregate comes, nor leaves, inline
      for (const id of items.keys()) if (id.startsWith("~")) items.delete(id);
      this.aggregatesHeld = 0;
    }
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
    if (this.tiled) this.setSheet(answer.tiles ? { ...answer.tiles, version: answer.version } : null);
    this.apply(answer);
    request.band = answer.band; // the zoom band of its aggregates: a later diff starts from it
    this.answered = request;
    this.truncated = answer.truncated;
    this.done = request.seq;
    this.rtt = performance.now() - request.at;
    if (this.tiled) {
      this.fetchTiles();
      if (answer.tiles === undefined) this.zoomOut(this.aggregatesHeld, this.items.size - this.aggregatesHeld);
      else if (!this.tileLoads.size && this.tilesComplete) this.countTiled(); // else once its tiles are in
    }
    this.status();
  }

  /** The view shows `aggregates` and `items`: zoomed out when they are many aggregates (see
   * TILED_LEAST), tiled, it is asked over HTTP with tiles, and the stream is left; zoomed in,
   * the stream is opened again. */
  zoomOut(/** @type {number} */ aggregates, /** @type {number} */ items) {
    const k = this.zoomedOut ? 0.5 : 1;
    const out = aggregates >= k * TILED_LEAST && aggregates >= k * TILED_SHARE * items;
    if (out === this.zoomedOut) return;
    this.zoomedOut = out;
    this.generation++;
    if (out && this.transport === "ws") this.leaveStream();
    else if (!out && this.transport === "http" && !this.ws && this.wantsStream()) this.connect();
  }

  /** @param {string | null} [error] */
  status(error = null) {
    /** @type {Status} */
    const s = { transport: this.transport, live: this.live, reconnecting: this.reconnecting, rtt: this.rtt,
                version: this.version, error };  // prettier-ignore
    if (this.onStatus) this.onStatus(s);
    this.dispatchEvent(new CustomEvent("status", { detail: s }));
  }

  // -- tiles: zoomed out, the aggregates in squares fixed in canvas space -------------------

  /** The tiles near the screen (`tileRange`) of those the answer held names that are held
   * (decoded), row by row: what to draw zoomed out, with `layerOrder()` and `tileAggregates()`.
   * Empty zoomed in or without `tiles: true`. Cost: O(tiles near the screen), once a generation.
   * @returns {Tile[]} */
  tiles() {
    const sheet = this.sheet;
    if (!sheet) return [];
    if (this.tileList.of !== this.generation) {
      const tiles = [];
      for (const [tx, ty] of tilesIn(this.tileRange)) {
        const tile = this.tileCache.get(this.tilePath(sheet, tx, ty));
        if (tile) tiles.push(tile);
      }
      this.tileList = { of: this.generation, tiles };
    }
    return this.tileList.tiles;
  }

  /** Whether every tile near the screen of those the answer held names is held. */
  get tilesComplete() {
    return !this.sheet || this.tiles().length === this.named.size;
  }

  /** The aggregates of `tiles`, once each (one touching two tiles is listed in both), as items:
   * `agg` holds their count and cover, `boxed` marks those without bits in the layers (draw
   * their box, as dense as `cover`). @returns {(Item & {boxed: boolean})[]} */
  tileAggregates(tiles = this.tiles()) {
    if (this.tileItems.tiles === tiles) return /** @type {any} */ (this.tileItems.items);
    /** @type {Map<string, Item & {boxed: boolean}>} */
    const seen = new Map();
    for (const tile of tiles) {
      const a = tile.aggregates, boxed = new Set(a.boxed), s = tile.scale;
      const px = tile.tx * tile.size, py = tile.ty * tile.size;  // its corner, in its scale's pixels
      for (let i = 0; i < a.index.length; i++) {
        const id = `~${tile.band}.${a.index[i]}`;
        if (seen.has(id)) continue;
        const [c0, r0, c1, r1] = a.box.slice(4 * i, 4 * i + 4);
        seen.set(id, { id, x0: (px + c0) / s, y0: (py + r0) / s, x1: (px + c1) / s, y1: (py + r1) / s, kind: a.kind[i],
                       z: a.z[i], agg: { count: a.count[i], cover: a.cover[i] / 1000 }, boxed: boxed.has(i) });  // prettier-ignore
      }
    }
    this.tileItems = { tiles, items: [...seen.values()] };
    return this.tileItems.items;
  }

  /** The kinds of `tiles`' layers, to draw in this order: by the highest z of their aggregates,
   * then as `names` lists them. @returns {{kind: string, z: number}[]} */
  layerOrder(tiles = this.tiles(), /** @type {string[]} */ names = []) {
    /** @type {Map<string, number>} */
    const top = new Map();
    for (const tile of tiles) {
      const a = tile.aggregates;
      for (const kind of tile.layers.keys()) if (!top.has(kind)) top.set(kind, -Infinity);
      for (let i = 0; i < a.kind.length; i++) {
        if (tile.layers.has(a.kind[i])) top.set(a.kind[i], Math.max(/** @type {number} */ (top.get(a.kind[i])), a.z[i]));
      }
    }
    const rank = (/** @type {string} */ kind) => (names.includes(kind) ? names.indexOf(kind) : names.length);
    return [...top].map(([kind, z]) => ({ kind, z: Number.isFinite(z) ? z : 0 }))
      .sort((a, b) => a.z - b.z || rank(a.kind) - rank(b.kind) || (a.kind < b.kind ? -1 : a.kind > b.kind ? 1 : 0));
  }

  /** The path (and query) of `sheet`'s tile at (tx, ty): the key it is held by. */
  tilePath(/** @type {Sheet} */ sheet, /** @type {number} */ tx, /** @type {number} */ ty) {
    return this.docPath(`/tiles/${sheet.band}/${sheet.z}/${tx}/${ty}?version=${sheet.version}`);
  }

  setSheet(/** @type {Sheet | null} */ sheet) {
    const old = this.sheet;
    if (old && sheet && old.band === sheet.band && old.z === sheet.z && old.version === sheet.version &&
        old.range.every((v, i) => v === sheet.range[i])) return;  // prettier-ignore
    this.sheet = sheet;
    this.tileRange = null;
    this.named = new Set();
    this.aimTiles();
    this.generation++;
  }

  /** Aim at the screen (the last view()'s): of the tiles the answer names, those touching it or
   * its overscan margin (`tilesNear`) are the ones `named`, fetched and drawn. Cost: O(those),
   * whatever the answer's range. @returns {boolean} whether they changed */
  aimTiles() {
    const sheet = this.sheet, screen = this.screen || (this.answered && this.answered.rect);
    const range = sheet && screen ? tilesNear(sheet, screen, this.scale, this.policy.overscan) : null;
    const old = this.tileRange;
    if (old === range || (old && range && old.every((v, i) => v === range[i]))) return false;
    this.tileRange = range;
    this.named = new Set([...tilesIn(range)].map(([tx, ty]) => this.tilePath(/** @type {Sheet} */ (sheet), tx, ty)));
    this.generation++;
    return true;
  }

  /** Fetch the tiles `named` that are not held, those nearest the screen first, TILE_LOADS at
   * a time (each one in starts the next); drop the fetches of tiles no longer named. A tile held
   * is never fetched again. */
  fetchTiles() {
    const sheet = this.sheet, range = this.tileRange, now = performance.now();
    for (const [path, control] of this.tileLoads) {
      if (!this.named.has(path)) {
        control.abort();
        this.tileLoads.delete(path);
      }
    }
    for (const path of this.tileRetry.keys()) if (!this.named.has(path)) this.tileRetry.delete(path);
    if (!sheet || !range) return;
    const side = sheet.size / ladderScale(sheet.z), screen = this.screen || this.answered?.rect || [0, 0, 0, 0];
    const cx = (screen[0] + screen[2]) / 2 / side - 0.5, cy = (screen[1] + screen[3]) / 2 / side - 0.5;
    const near = [...tilesIn(range)].sort(([ax, ay], [bx, by]) => (ax - cx) ** 2 + (ay - cy) ** 2 - (bx - cx) ** 2 - (by - cy) ** 2);
    for (const [tx, ty] of near) {
      const path = this.tilePath(sheet, tx, ty), held = this.tileCache.get(path);
      if (held) {  // named again: the most recently named
        this.tileCache.delete(path);
        this.tileCache.set(path, held);
      } else if (this.tileLoads.size < TILE_LOADS && !this.tileLoads.has(path) && !((this.tileRetry.get(path) ?? 0) > now)) {
        this.loadTile(path);
      }
    }
    this.keepTiles();
  }

  /** Fetch one tile and decode it. The same tile held at another version is revalidated: a 304
   * keeps it (same origin only: `If-None-Match` is not a header CORS lets through). */
  async loadTile(/** @type {string} */ path) {
    const control = new AbortController(), doc = this.doc, at = path.split("?")[0];
    this.tileLoads.set(path, control);
    this.tileFetches++;
    const prior = this.tileCache.get(this.tileAt.get(at) ?? "");
    const sameOrigin = !!globalThis.location && this.url === location.origin;
    const headers = prior && prior.etag && sameOrigin ? { "If-None-Match": prior.etag } : undefined;
    try {
      const response = await this.request(path, { signal: control.signal, headers });
      let tile;
      if (response.status === 304 && prior) {
        tile = { ...prior, path };
      } else if (response.ok) {
        tile = await decodeTile(await response.json(), path, response.headers.get("ETag"));
      } else {
        const body = await response.json().catch(() => null);
        throw new VantageError(response.status, typeof body?.detail === "string" ? body.detail : `HTTP ${response.status}`);
      }
      if (this.tileLoads.get(path) !== control || doc !== this.doc) return;
      this.tileCache.set(path, tile);
      this.tileAt.set(at, path);
      this.tileRetry.delete(path);
      this.keepTiles();
    } catch (error) {
      if (control.signal.aborted || doc !== this.doc) return;
      this.tileRetry.set(path, performance.now() + this.policy.pollMs);  // asked again at a poll's answer
      // 409: an edit since the answer changed the tile; the next poll names it at a newer version
      if (error instanceof VantageError && error.status === 409) this.poll();
      else this.status(`tile ${at}: ${/** @type {any} */ (error).message || error}`);
    } finally {
      if (this.tileLoads.get(path) === control) {
        this.tileLoads.delete(path);
        this.generation++; // the tiles held changed (or one was given up on): the picture did
        this.fetchTiles(); // the next ones
        if (!this.tileLoads.size && this.tilesComplete) this.countTiled();
        this.dispatchEvent(new CustomEvent("tiles"));
      }
    }
  }

  /** Zoomed out still? The tiles' aggregates against the items, both in the rect answered and
   * near the screen (where the tiles held are, that rect stretched ahead of a fast move); no
   * telling when the screen has left that rect (the next answer tells). */
  countTiled() {
    const answered = this.answered ? this.answered.rect : null;
    if (!answered) return;
    const near = this.screen ? grown(this.screen, this.policy.overscan) : answered;
    const rect = [Math.max(answered[0], near[0]), Math.max(answered[1], near[1]),
                  Math.min(answered[2], near[2]), Math.min(answered[3], near[3])];  // prettier-ignore
    if (!(rect[0] <= rect[2] && rect[1] <= rect[3])) return;
    const touches = (/** @type {Item} */ a) => a.x0 <= rect[2] && a.x1 >= rect[0] && a.y0 <= rect[3] && a.y1 >= rect[1];
    let shown = 0, items = 0;
    for (const a of this.tileAggregates()) if (touches(a)) shown++;
    for (const item of this.items.values()) if (touches(item)) items++;
    this.zoomOut(shown, items);
  }

  /** Drop the least recently named tiles past TILE_MOST, never one `named` (near the screen). */
  keepTiles() {
    for (const path of this.tileCache.keys()) {
      if (this.tileCache.size <= TILE_MOST) return;
      if (this.named.has(path)) continue;
      this.tileCache.delete(path);
      const at = path.split("?")[0];
      if (this.tileAt.get(at) === path) this.tileAt.delete(at);
    }
  }

  // -- transports --------------------------------------------------------------------------

  connect() {
    clearTimeout(this.retryTimer);
    this.retryTimer = null;
    if (!this.wantsStream()) return;
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

  /** Whether views should go over the stream: not after useHttp(), nor zoomed out with tiles
   * (the stream answers aggregates inline). */
  wantsStream() {
    return !this.forcedHttp && !(this.tiled && this.zoomedOut);
  }

  retryLater() {
    if (!this.wantsStream() || this.retryTimer) return;
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

  /** Zoomed out with tiles: views over HTTP diffs (tiled), edits by polling, until zoomed in. */
  leaveStream() {
    const ws = this.ws;
    this.ws = null;
    if (ws) ws.close();
    clearTimeout(this.retryTimer);
    this.retryTimer = null;
    this.live = false;
    this.fallBack();
    this.poll(); // the view held, asked again tiled: its aggregates leave for tiles
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
    const tiled = this.tiled && this.zoomedOut ? "&tiles=true" : "";
    const common = `scale=${to.scale}&min_px=${policy.minPx}&limit=${policy.limit}${tiled}`;
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

/** Each (tx, ty) of an inclusive range of tiles (none for null), row by row.
 * @returns {Generator<[number, number]>} */
function* tilesIn(/** @type {[number, number, number, number] | null} */ range) {
  if (!range) return;
  const [tx0, ty0, tx1, ty1] = range;
  for (let ty = ty0; ty <= ty1; ty++) for (let tx = tx0; tx <= tx1; tx++) yield [tx, ty];
}

/**
 * The tiles of `sheet`'s range touching `screen` grown by `overscan` of its size on each side
 * (the margin a request asks for, without the stretch ahead of a move): the intersection of
 * the two ranges, worked out from their ends, so a range of millions of tiles costs nothing.
 * Along each side, at most twice as many as that margin spans at `scale` (the screen's pixels
 * a unit), around its middle: a screen zoomed far out since the answer waits for the next one.
 * @param {Sheet} sheet
 * @param {Rect} screen
 * @param {number} scale
 * @param {number} overscan
 * @returns {[number, number, number, number] | null}  tx0, ty0, tx1, ty1, inclusive; null for none
 */
function tilesNear(sheet, screen, scale, overscan) {
  const near = grown(screen, overscan), s = ladderScale(sheet.z), [tx0, ty0, tx1, ty1] = sheet.range;
  // As the server numbers them: floor(edge * scale / size), touching counting (closed intervals).
  const x = along(near[0] * s / sheet.size, near[2] * s / sheet.size, tx0, tx1, (2 * (near[2] - near[0]) * scale) / sheet.size);
  const y = along(near[1] * s / sheet.size, near[3] * s / sheet.size, ty0, ty1, (2 * (near[3] - near[1]) * scale) / sheet.size);
  return x && y ? [x[0], y[0], x[1], y[1]] : null;
}

/** The tiles `lo` to `hi` (inclusive) that the span from `a` to `b` (in tiles) touches, at most
 * `Math.ceil(most) + 1` of them around its middle; null for none. @returns {[number, number] | null} */
function along(/** @type {number} */ a, /** @type {number} */ b, /** @type {number} */ lo, /** @type {number} */ hi,
               /** @type {number} */ most) {  // prettier-ignore
  let first = Math.max(lo, Math.floor(a)), last = Math.min(hi, Math.floor(b));
  if (!(first <= last)) return null;
  const n = Math.ceil(most) + 1;
  if (last - first + 1 > n) {
    first = Math.min(Math.max(first, Math.floor((a + b) / 2 - n / 2)), last - n + 1);
    last = first + n - 1;
  }
  return [first, last];
}

/**
 * A tile URL's JSON, decoded: each layer inflated (zlib, by the browser's DecompressionStream)
 * to its `size * size` bits, once.
 * @param {any} body  the tile URL's JSON
 * @param {string} [path]  its URL's path, the key it is held and drawn by
 * @param {string | null} [etag]
 * @returns {Promise<Tile>}
 * @throws {Error} if a layer does not inflate to `size * size` bits
 */
export async function decodeTile(body, path = "", etag = null) {
  const { band, z, tx, ty, scale, box, size, aggregates } = body;
  const kinds = Object.keys(body.layers || {});
  const bits = await Promise.all(kinds.map((kind) => inflate(body.layers[kind])));
  /** @type {Map<string, Uint8Array>} */
  const layers = new Map();
  kinds.forEach((kind, i) => {
    if (bits[i].length !== (size * size) / 8) {
      throw new Error(`tile ${band}/${z}/${tx}/${ty}: layer ${kind} holds ${bits[i].length} bytes, not ${(size * size) / 8}`);
    }
    layers.set(kind, bits[i]);
  });
  return { path, etag, band, z, tx, ty, scale, box, size, aggregates, layers };
}

/** base64 of zlib-deflated bytes, inflated. @returns {Promise<Uint8Array>} */
async function inflate(/** @type {string} */ text) {
  const packed = Uint8Array.from(atob(text), (c) => c.charCodeAt(0));
  const stream = new Blob([packed]).stream().pipeThrough(new DecompressionStream("deflate"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

/**
 * @typedef {object} TileImage  a tile's layer as drawn at one scale and sub-pixel offset
 * @property {HTMLCanvasElement | OffscreenCanvas} canvas
 * @property {number} cs  device pixels a bit
 * @property {number} px  where the tile's corner falls within its first pixel, x
 * @property {number} py  and y
 * @property {string} slot  the tile, kind and colour it is of
 */

/**
 * Draws tiles' layers: every set bit inks every device pixel it touches (a bit smaller than a
 * pixel still inks it; one across a pixel edge inks both), never sampled (which would drop the
 * bits smaller than a pixel). At the tile's own scale, its corner on a pixel's corner, that is
 * a pixel a bit. A tile's layer is made once an image of its footprint on screen, for each
 * scale and offset within a pixel, and drawn at whole pixels: panning by whole pixels draws the
 * same images again. Call `frame()` once a frame: new images are made for RENDER_MS of it, past
 * that a layer's last image is stretched in its place (`exact` turns false) and the next frame
 * makes it.
 */
export class TilePainter {
  constructor({ most = IMAGE_MOST, renderMs = RENDER_MS } = {}) {
    this.most = most; // pixels of images kept
    this.renderMs = renderMs;
    /** @type {Map<string, TileImage>} */ this.images = new Map(); // least recently drawn first
    /** @type {Map<string, string>} */ this.latest = new Map(); // slot -> its newest image's key
    /** @type {Map<string, number>} */ this.inks = new Map(); // CSS colour -> RGBA as a pixel
    this.pixels = 0;
    this.until = Infinity;
    this.exact = true; // every layer drawn since frame() was drawn exactly
  }

  /** A new frame. */
  frame(now = performance.now()) {
    this.until = now + this.renderMs;
    this.exact = true;
  }

  /**
   * Draw `tile`'s layer of `kind` in `colour` on `ctx`, for a view whose top-left is the canvas
   * point (x, y) at `scale` CSS pixels a unit (under `ctx`'s transform: device pixels are ruled).
   * @param {CanvasRenderingContext2D} ctx
   * @param {Tile} tile
   * @param {string} kind
   * @param {string} colour  a CSS colour
   * @param {number} x
   * @param {number} y
   * @param {number} scale
   * @returns {boolean} false when a stretched stand-in was drawn (drawn exactly next frame)
   */
  draw(ctx, tile, kind, colour, x, y, scale) {
    const bits = tile.layers.get(kind);
    if (!bits) return true;
    const m = ctx.getTransform(), s = scale * m.a, cs = s / tile.scale, side = tile.size * cs;
    // Subtract in float64 first, then scale: only small numbers reach the canvas.
    const fx = (tile.box[0] - x) * s + m.e, fy = (tile.box[1] - y) * s + m.f;
    if (!(side > 0) || fx > ctx.canvas.width || fy > ctx.canvas.height || fx + side < 0 || fy + side < 0) return true;
    const slot = `${tile.etag || tile.path}|${kind}|${colour}`;
    ctx.save();
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.imageSmoothingEnabled = false;
    try {
      if (side > SCALED_PAST) {  // bits of 4 pixels and more: a pixel a bit, scaled
        ctx.drawImage(this.image(`${slot}|cells`, slot, bits, tile.size, 1, 0, 0, colour).canvas, fx, fy, side, side);
        return true;
      }
      let ix = Math.floor(fx), iy = Math.floor(fy);
      let px = Math.round((fx - ix) * PHASE_STEPS) / PHASE_STEPS, py = Math.round((fy - iy) * PHASE_STEPS) / PHASE_STEPS;
      if (px === 1) [ix, px] = [ix + 1, 0];
      if (py === 1) [iy, py] = [iy + 1, 0];
      const key = `${slot}|${s}|${px}|${py}`;
      const standIn = this.images.has(key) ? null : this.images.get(this.latest.get(slot) ?? "");
      if (standIn && performance.now() > this.until) {  // out of this frame's time: the last one, stretched
        const k = cs / standIn.cs;
        ctx.drawImage(standIn.canvas, fx - standIn.px * k, fy - standIn.py * k, standIn.canvas.width * k, standIn.canvas.height * k);
        this.exact = false;
        return false;
      }
      ctx.drawImage(this.image(key, slot, bits, tile.size, cs, px, py, colour).canvas, ix, iy);
      return true;
    } finally {
      ctx.restore();
    }
  }

  /** The image at `key`: kept, or made now (and the least recently drawn dropped past `most`).
   * @returns {TileImage} */
  image(/** @type {string} */ key, /** @type {string} */ slot, /** @type {Uint8Array} */ bits, /** @type {number} */ size,
        /** @type {number} */ cs, /** @type {number} */ px, /** @type {number} */ py, /** @type {string} */ colour) {  // prettier-ignore
    const held = this.images.get(key);
    if (held) {
      this.images.delete(key);
      this.images.set(key, held);
      return held;
    }
    const w = Math.max(1, Math.ceil(px + size * cs)), h = Math.max(1, Math.ceil(py + size * cs));
    const canvas = typeof OffscreenCanvas === "function" ? new OffscreenCanvas(w, h) : Object.assign(document.createElement("canvas"), { width: w, height: h });
    const pixels = inked(bits, size, cs, px, py, w, h, this.ink(colour));
    /** @type {CanvasRenderingContext2D} */ (canvas.getContext("2d")).putImageData(new ImageData(new Uint8ClampedArray(pixels.buffer), w, h), 0, 0);
    const image = { canvas, cs, px, py, slot };
    this.images.set(key, image);
    if (!key.endsWith("|cells")) this.latest.set(slot, key);
    this.pixels += w * h;
    for (const [old, dropped] of this.images) {
      if (this.pixels <= this.most || old === key) break;
      this.images.delete(old);
      this.pixels -= dropped.canvas.width * dropped.canvas.height;
      if (this.latest.get(dropped.slot) === old) this.latest.delete(dropped.slot);
    }
    return image;
  }

  /** `colour` as one pixel of an ImageData's buffer, read as a Uint32. */
  ink(/** @type {string} */ colour) {
    let ink = this.inks.get(colour);
    if (ink === undefined) {
      const probe = typeof OffscreenCanvas === "function" ? new OffscreenCanvas(1, 1) : Object.assign(document.createElement("canvas"), { width: 1, height: 1 });
      const ctx = /** @type {CanvasRenderingContext2D} */ (probe.getContext("2d"));
      ctx.fillStyle = colour;
      ctx.fillRect(0, 0, 1, 1);
      const [r, g, b] = ctx.getImageData(0, 0, 1, 1).data;  // the colour, as the canvas parses it
      ink = LITTLE_ENDIAN ? ((255 << 24) | (b << 16) | (g << 8) | r) >>> 0 : ((r << 24) | (g << 16) | (b << 8) | 255) >>> 0;
      this.inks.set(colour, ink);
    }
    return ink;
  }
}

/** The pixels (`w` x `h`, a Uint32 each) a layer's set bits touch, `cs` pixels a bit, its
 * corner at (`px`, `py`) within the first pixel: a run of set bits in a row fills, on each
 * pixel row its bits touch, from the pixel its first bit starts in to the one its last ends in. */
function inked(/** @type {Uint8Array} */ bits, /** @type {number} */ size, /** @type {number} */ cs, /** @type {number} */ px,
               /** @type {number} */ py, /** @type {number} */ w, /** @type {number} */ h, /** @type {number} */ ink) {  // prettier-ignore
  const [left, right] = spans(size, cs, px, w), [top, bottom] = spans(size, cs, py, h);
  const pixels = new Uint32Array(w * h), stride = size >> 3;
  for (let r = 0; r < size; r++) {
    const row = r * stride, y0 = top[r], y1 = bottom[r];
    const fill = (/** @type {number} */ first, /** @type {number} */ last) => {
      for (let y = y0; y < y1; y++) pixels.fill(ink, y * w + left[first], y * w + right[last]);
    };
    let start = -1;
    for (let b = 0; b < stride; b++) {
      const byte = bits[row + b];
      if (byte === 0 || byte === 255) {  // a whole byte empty or set: a run ends, or goes on
        if (byte === 0 && start >= 0) fill(start, (b << 3) - 1), (start = -1);
        else if (byte === 255 && start < 0) start = b << 3;
        continue;
      }
      for (let bit = 0; bit < 8; bit++) {
        const i = (b << 3) | bit;
        if (byte & (1 << bit)) {
          if (start < 0) start = i;
        } else if (start >= 0) {
          fill(start, i - 1);
          start = -1;
        }
      }
    }
    if (start >= 0) fill(start, size - 1);
  }
  return pixels;
}

/** For each of `size` bits of `cs` pixels from `p`: the first pixel it touches, and the one
 * past the last (at most `limit`). @returns {[Int32Array, Int32Array]} */
function spans(/** @type {number} */ size, /** @type {number} */ cs, /** @type {number} */ p, /** @type {number} */ limit) {
  const first = new Int32Array(size), past = new Int32Array(size);
  for (let i = 0; i < size; i++) {
    first[i] = Math.floor(p + i * cs + EDGE);
    past[i] = Math.min(limit, Math.max(first[i] + 1, Math.ceil(p + (i + 1) * cs - EDGE)));
  }
  return [first, past];
}
