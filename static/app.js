// Vantage canvas: pan and zoom a document the server holds, keeping only what is near the screen.
//
// Every frame is drawn from the local set `held`; the network only feeds that set. The page asks
// for the screen plus an overscan margin, and asks again only when the screen nears the margin's
// edge or the zoom changes the level of detail, so items are there before they scroll in.
"use strict";

// The fetch policy, static/policy.json, which the simulator (app/simulate/policy.py) reads too;
// start() loads it before opening a document. Its fields:
//   overscan    margin on each side, as a share of the screen
//   refetchAt   ask again when the screen is closer than this share to the margin's edge
//   lodStep     ask again when the zoom changed by more than this factor
//   lookaheadS  also ask for where the screen will be this far ahead at its current speed
//   smoothingS  the screen's velocity is smoothed over this many seconds
//   minPx       items under this many pixels on screen are not shipped
//   limit       items per answer
//   pollMs      over HTTP, how often to ask for edits by others
let POLICY = null;

const COLOURS = {            // fill, stroke by kind
  page: ["#ffffff", "#b9bec8"], text: ["#5b6270", null], image: ["#8fb3d9", null],
  note: ["#ffd866", "#d9a800"], frame: [null, "#7a5cff"], box: ["#5aa469", null],
};

const $ = (id) => document.getElementById(id);
// With VANTAGE_READ_TOKEN set, open the page as /?token=...: sent as a header, and in the
// stream's URL (a browser cannot set a WebSocket's headers).
const TOKEN = new URLSearchParams(location.search).get("token");
const api = (url) => fetch(url, TOKEN ? { headers: { Authorization: `Bearer ${TOKEN}` } } : undefined);
const canvas = $("canvas"), ctx = canvas.getContext("2d");

const state = {
  doc: null, bounds: null, version: 0,
  cam: { x: 0, y: 0, scale: 1 },      // the canvas point at the screen's top-left; pixels per unit
  velocity: { x: 0, y: 0 }, last: null, // units per second, smoothed: a fling is fetched ahead
  held: new Map(),                    // id -> item: what the server sent for `requested`
  order: [],                          // held items by z, rebuilt when `held` changes
  dirty: true,
  generation: 0,                      // bumped whenever `held` changes
  painted: null,                      // what the last frame was drawn from: see draw()
  goto: { started: 0, done: 0, pending: 0, last: null },  // "go to"s: counts, and how the last one ended
  requested: null,                    // { rect, scale } last asked for
  answered: null,                     // the request whose answer `held` reflects
  sent: 0, done: 0, sentAt: new Map(), truncated: false,
  rtt: 0, lastDiff: 0, fps: 0, frames: [],
  transport: "ws", ws: null, busy: false, pollTimer: null,
  cells: [], showCells: false, cellsAt: 0,
};

// -- geometry --------------------------------------------------------------------------

function screenRect() {
  const { x, y, scale } = state.cam;
  return [x, y, x + canvas.clientWidth / scale, y + canvas.clientHeight / scale];
}

function grown(rect, share) {
  const dx = (rect[2] - rect[0]) * share, dy = (rect[3] - rect[1]) * share;
  return [rect[0] - dx, rect[1] - dy, rect[2] + dx, rect[3] + dy];
}

function inside(inner, outer) {
  return inner[0] >= outer[0] && inner[1] >= outer[1] && inner[2] <= outer[2] && inner[3] <= outer[3];
}

function ahead(rect, seconds) {
  // ``rect`` stretched towards where the screen is heading in ``seconds``.
  const dx = state.velocity.x * seconds, dy = state.velocity.y * seconds;
  return [rect[0] + Math.min(dx, 0), rect[1] + Math.min(dy, 0), rect[2] + Math.max(dx, 0), rect[3] + Math.max(dy, 0)];
}

function needsRequest() {
  const req = state.requested;
  if (!req) return true;
  const ratio = state.cam.scale / req.scale;
  if (ratio > POLICY.lodStep || ratio < 1 / POLICY.lodStep) return true;
  const safe = grown(req.rect, -POLICY.refetchAt * POLICY.overscan / (1 + 2 * POLICY.overscan));
  return !inside(ahead(screenRect(), POLICY.lookaheadS / 2), safe);
}

function track(now) {
  const { cam, last, velocity } = state;
  if (last && now > last.t) {
    const dt = (now - last.t) / 1000, k = Math.min(1, dt / POLICY.smoothingS);
    velocity.x += k * ((cam.x - last.x) / dt - velocity.x);
    velocity.y += k * ((cam.y - last.y) / dt - velocity.y);
    if (cam.scale !== last.scale) velocity.x = velocity.y = 0;  // a zoom is not a fling
  }
  state.last = { t: now, x: cam.x, y: cam.y, scale: cam.scale };
}

// -- the camera ------------------------------------------------------------------------

function panBy(dxPx, dyPx) {
  state.cam.x += dxPx / state.cam.scale;  // float64 throughout: no drift far from the origin
  state.cam.y += dyPx / state.cam.scale;
}

function zoomAt(px, py, factor) {
  const { cam } = state;
  const ux = cam.x + px / cam.scale, uy = cam.y + py / cam.scale;
  cam.scale = Math.min(1e6, Math.max(1e-12, cam.scale * factor));
  cam.x = ux - px / cam.scale;
  cam.y = uy - py / cam.scale;
}

function centreOn(x, y, scale = state.cam.scale) {
  state.cam.scale = scale;
  state.cam.x = x - canvas.clientWidth / 2 / scale;
  state.cam.y = y - canvas.clientHeight / 2 / scale;
}

function fit(wholeDocument) {
  const b = state.bounds;
  if (!b) return centreOn(0, 0, 1);
  const w = Math.max(b[2] - b[0], 1e-9), h = Math.max(b[3] - b[1], 1e-9);
  const W = canvas.clientWidth, H = canvas.clientHeight;
  if (!wholeDocument && h > 4 * w) {  // a long document: its width on screen, from the top
    const scale = Math.min(W / w, 2) * 0.95;
    state.cam.scale = scale;
    state.cam.x = (b[0] + b[2]) / 2 - W / 2 / scale;
    state.cam.y = b[1] - 10 / scale;
  } else {
    centreOn((b[0] + b[2]) / 2, (b[1] + b[3]) / 2, Math.min(W / w, H / h) * 0.95);
  }
}

// -- the held set ------------------------------------------------------------------------

function apply(answer) {
  if (answer.reset) state.held.clear();
  for (const id of answer.leave) state.held.delete(id);
  for (const item of answer.enter) state.held.set(item.id, item);
  state.version = answer.version;
  state.lastDiff = answer.enter.length + answer.leave.length;
  heldChanged();
}

function heldChanged() {
  state.generation++;
  state.dirty = true;
}

function answered(request, answer) {
  apply(answer);
  request.band = answer.band;  // the zoom band of its aggregates: a later diff starts from it
  state.answered = request;
  state.truncated = answer.truncated;
  state.done = request.seq;
  state.rtt = performance.now() - request.at;
}

function nextRequest() {
  const rect = ahead(grown(screenRect(), POLICY.overscan), POLICY.lookaheadS);
  return { seq: ++state.sent, rect, scale: state.cam.scale, at: performance.now() };
}

function request() {
  if (!state.doc) return;
  if (state.transport === "ws") {
    if (!state.ws || state.ws.readyState !== WebSocket.OPEN) return;
    const req = nextRequest();
    state.sentAt.set(req.seq, req);
    state.requested = req;
    state.ws.send(JSON.stringify({ seq: req.seq, viewport: req.rect, scale: req.scale, min_px: POLICY.minPx, limit: POLICY.limit }));
  } else if (!state.busy) {
    const req = nextRequest();
    state.requested = req;
    fetchDiff(state.answered, req);
  }
}

function connect() {
  const query = TOKEN ? `?token=${encodeURIComponent(TOKEN)}` : "";
  const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/documents/${state.doc}/stream${query}`;
  const ws = new WebSocket(url);
  state.ws = ws;
  ws.onopen = () => { state.requested = null; state.answered = null; };
  ws.onmessage = (event) => {
    if (ws !== state.ws) return;
    const msg = JSON.parse(event.data);
    if (msg.type === "error") return showError(msg.message);
    if (msg.type === "edit") return apply(msg);
    const req = state.sentAt.get(msg.seq);
    for (const seq of state.sentAt.keys()) if (seq <= msg.seq) state.sentAt.delete(seq);  // superseded ones too
    if (req) answered(req, msg);
  };
  ws.onclose = (event) => {
    if (ws !== state.ws) return;
    if (event.code === 4404) return showError(event.reason || "document not found");
    useHttp();  // no stream (a proxy without WebSockets, say): diffs over HTTP, and polling for edits
  };
}

function useHttp() {
  state.transport = "http";
  state.ws = null;
  state.requested = state.answered;
  clearInterval(state.pollTimer);
  state.pollTimer = setInterval(() => {  // the same view again: only edits since our version come back
    if (state.busy || !state.answered || needsRequest()) return;
    state.requested = { ...state.answered, seq: ++state.sent, at: performance.now() };
    fetchDiff(state.answered, state.requested);
  }, POLICY.pollMs);
}

async function fetchDiff(from, to) {
  state.busy = true;
  const doc = state.doc;
  const common = `scale=${to.scale}&min_px=${POLICY.minPx}&limit=${POLICY.limit}`;
  const url = from
    ? `/documents/${doc}/diff?from=${from.rect.join(",")}&to=${to.rect.join(",")}&from_scale=${from.scale}&${common}` +
      `&since=${state.version}${from.band == null ? "" : `&from_band=${from.band}`}`
    : `/documents/${doc}/viewport?x0=${to.rect[0]}&y0=${to.rect[1]}&x1=${to.rect[2]}&y1=${to.rect[3]}&${common}`;
  try {
    const response = await api(url);
    const body = await response.json();
    if (!response.ok) throw new Error(body.detail || response.statusText);
    if (doc !== state.doc) return;
    if (!from) { body.reset = true; body.leave = []; body.enter = body.items; }
    answered(to, body);
  } catch (error) {
    showError(String(error.message || error));
  } finally {
    state.busy = false;
  }
}

// -- drawing -----------------------------------------------------------------------------

function draw(now) {
  const dpr = window.devicePixelRatio || 1;
  const W = canvas.clientWidth, H = canvas.clientHeight;
  if (canvas.width !== Math.round(W * dpr) || canvas.height !== Math.round(H * dpr)) {
    canvas.width = Math.round(W * dpr);
    canvas.height = Math.round(H * dpr);
  }
  track(now);
  if (needsRequest()) request();
  if (state.dirty) {
    state.order = [...state.held.values()].sort((a, b) => (a.z ?? 0) - (b.z ?? 0));
    state.dirty = false;
  }
  const generation = state.generation;  // `order` is `held` as of this generation
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.fillStyle = "#e9ebee";
  ctx.fillRect(0, 0, W, H);
  const { x, y, scale } = state.cam;
  let shown = 0, standing = 0;
  for (const item of state.order) {
    // Subtract in float64 first, then scale: only small numbers reach the canvas.
    const sx = (item.x0 - x) * scale, sy = (item.y0 - y) * scale;
    const sw = Math.max((item.x1 - item.x0) * scale, 1), sh = Math.max((item.y1 - item.y0) * scale, 1);
    if (sx > W || sy > H || sx + sw < 0 || sy + sh < 0) continue;
    shown++;
    const [fill, stroke] = COLOURS[item.kind] || COLOURS.box;
    if (item.agg) {  // stands in for items too small to draw: their kind, as dense as they cover its box
      standing += item.agg.count;
      ctx.globalAlpha = 0.35 + 0.65 * item.agg.cover;
      ctx.fillStyle = fill || stroke;
      ctx.fillRect(sx, sy, sw, sh);
      ctx.globalAlpha = 1;
      continue;
    }
    if (fill) {
      ctx.fillStyle = fill;
      if (item.kind === "text") ctx.fillRect(sx, sy + sh * 0.2, sw, Math.max(sh * 0.6, 1));
      else ctx.fillRect(sx, sy, sw, sh);
    }
    if (stroke && sw > 3 && sh > 3) {
      ctx.strokeStyle = stroke;
      ctx.strokeRect(sx + 0.5, sy + 0.5, sw - 1, sh - 1);
    }
  }
  if (state.showCells) drawCells();
  painted({ x, y, scale, generation, width: W, height: H, dpr });
  state.frames.push(now);
  while (state.frames.length && now - state.frames[0] > 1000) state.frames.shift();
  status(shown, standing);
  requestAnimationFrame(draw);
}

function painted(frame) {
  // Record what this frame was drawn from; `seq` counts frames that differ from the one before,
  // so an unchanged `seq` means the canvas still shows the same picture.
  const last = state.painted;
  if (last && sameFrame(last, frame)) return;
  state.painted = { seq: (last ? last.seq : 0) + 1, ...frame };
}

function canvasSize() {
  return { width: canvas.clientWidth, height: canvas.clientHeight, dpr: window.devicePixelRatio || 1 };
}

function sameFrame(a, b) {
  return a.x === b.x && a.y === b.y && a.scale === b.scale && a.generation === b.generation &&
    a.width === b.width && a.height === b.height && a.dpr === b.dpr;
}

function isDrawn() {
  // Whether the canvas shows the current camera over the current held set, at its current size.
  const now = { ...state.cam, generation: state.generation, ...canvasSize() };
  return !!state.painted && sameFrame(state.painted, now);
}

function drawCells() {
  const { x, y, scale } = state.cam;
  ctx.lineWidth = 1;
  for (const cell of state.cells) {
    const [x0, y0, x1, y1] = cell.box;
    ctx.strokeStyle = cell.leaf ? "rgba(220, 50, 47, 0.8)" : `hsla(${(cell.depth * 47) % 360}, 70%, 45%, 0.5)`;
    ctx.strokeRect((x0 - x) * scale, (y0 - y) * scale, Math.max((x1 - x0) * scale, 1), Math.max((y1 - y0) * scale, 1));
  }
  const now = performance.now();
  if (now - state.cellsAt > 300) {
    state.cellsAt = now;
    const r = screenRect();
    api(`/documents/${state.doc}/cells?x0=${r[0]}&y0=${r[1]}&x1=${r[2]}&y1=${r[3]}&limit=3000`)
      .then((response) => response.json()).then((body) => { state.cells = body.cells || []; });
  }
}

let errorUntil = 0;
function showError(message) {
  errorUntil = performance.now() + 4000;
  $("status").textContent = message;
  $("status").className = "warn";
}

function status(shown, standing) {
  if (performance.now() < errorUntil) return;
  const el = $("status");
  el.className = state.truncated ? "warn" : "";
  const grouped = standing ? ` (${standing.toLocaleString()} too small to draw, shown grouped)` : "";
  el.textContent = `${shown.toLocaleString()} in view${grouped} · ${state.held.size.toLocaleString()} held` +
    `${state.truncated ? " (truncated: zoom in)" : ""} · last diff ${state.lastDiff} · ` +
    `${state.rtt.toFixed(0)} ms · ${state.frames.length} fps · v${state.version} · ${state.transport}`;
}

// -- input -------------------------------------------------------------------------------

const pointers = new Map();

canvas.addEventListener("pointerdown", (e) => {
  canvas.setPointerCapture(e.pointerId);
  pointers.set(e.pointerId, { x: e.offsetX, y: e.offsetY });
  canvas.classList.add("dragging");
  canvas.focus();
});

canvas.addEventListener("pointermove", (e) => {
  const last = pointers.get(e.pointerId);
  if (!last) return;
  if (pointers.size === 2) {  // pinch: zoom by the change in distance, around the midpoint
    const [a, b] = [...pointers.values()];
    const other = a === last ? b : a;
    const before = Math.hypot(last.x - other.x, last.y - other.y);
    const after = Math.hypot(e.offsetX - other.x, e.offsetY - other.y);
    if (before > 0) zoomAt((e.offsetX + other.x) / 2, (e.offsetY + other.y) / 2, after / before);
  } else {
    panBy(last.x - e.offsetX, last.y - e.offsetY);
  }
  pointers.set(e.pointerId, { x: e.offsetX, y: e.offsetY });
});

for (const type of ["pointerup", "pointercancel"]) {
  canvas.addEventListener(type, (e) => {
    pointers.delete(e.pointerId);
    if (!pointers.size) canvas.classList.remove("dragging");
  });
}

canvas.addEventListener("wheel", (e) => {
  e.preventDefault();
  const unit = e.deltaMode === 1 ? 16 : e.deltaMode === 2 ? canvas.clientHeight : 1;
  if (e.ctrlKey) zoomAt(e.offsetX, e.offsetY, Math.exp(-e.deltaY * unit * 0.01));  // ctrl+wheel, and trackpad pinch
  else panBy(e.deltaX * unit, e.deltaY * unit);
}, { passive: false });

window.addEventListener("keydown", (e) => {
  if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
  const step = e.shiftKey ? 600 : 60, H = canvas.clientHeight, W = canvas.clientWidth;
  const keys = {
    ArrowUp: () => panBy(0, -step), ArrowDown: () => panBy(0, step),
    ArrowLeft: () => panBy(-step, 0), ArrowRight: () => panBy(step, 0),
    PageUp: () => panBy(0, -H * 0.9), PageDown: () => panBy(0, H * 0.9), " ": () => panBy(0, H * 0.9),
    "+": () => zoomAt(W / 2, H / 2, 1.25), "=": () => zoomAt(W / 2, H / 2, 1.25), "-": () => zoomAt(W / 2, H / 2, 0.8),
    "0": () => fit(true), Home: () => fit(false),
  };
  if (keys[e.key]) { e.preventDefault(); keys[e.key](); }
});

$("fit").addEventListener("click", () => fit(true));
$("cells").addEventListener("change", (e) => { state.showCells = e.target.checked; state.cellsAt = 0; });
$("doc").addEventListener("change", (e) => open(e.target.value));
$("goto-form").addEventListener("submit", (e) => {
  e.preventDefault();
  goTo($("goto").value.trim());
});

async function goTo(text) {
  // Centre on "x, y", or on an item by id (fetched first: the camera moves when it arrives).
  // `state.goto` counts them, so a test or the console can tell when the camera has moved.
  const { goto } = state, seq = ++goto.started, doc = state.doc;
  goto.pending++;
  let outcome = "superseded";  // by a later "go to" or another document: this one moves nothing
  try {
    const coords = text.match(/^\s*(-?[\d.e+]+)\s*[, ]\s*(-?[\d.e+]+)\s*$/i);
    if (coords) {
      centreOn(Number(coords[1]), Number(coords[2]));
      outcome = "moved";
      return;
    }
    const response = await api(`/documents/${doc}/items/${encodeURIComponent(text)}`);
    if (seq !== goto.started || doc !== state.doc) return;
    if (!response.ok) {
      outcome = "not found";
      return showError(`no item ${JSON.stringify(text)} in this document`);
    }
    const item = await response.json();
    if (seq !== goto.started || doc !== state.doc) return;
    const size = Math.max(item.x1 - item.x0, item.y1 - item.y0, 1e-9);
    const readable = Math.min(canvas.clientWidth, canvas.clientHeight) / 3 / size;  // a third of the screen
    const scale = Math.min(readable, Math.max(state.cam.scale, readable / 8));  // zoom only as far as needed
    centreOn((item.x0 + item.x1) / 2, (item.y0 + item.y1) / 2, scale);
    outcome = "moved";
  } catch (error) {
    outcome = "failed";
    showError(String(error.message || error));
  } finally {
    goto.pending--;
    goto.done++;
    goto.last = { seq, text, outcome };
  }
}

// -- start -------------------------------------------------------------------------------

async function open(doc) {
  const response = await api(`/documents/${doc}`);
  if (!response.ok) return showError(`document ${doc} not found`);
  const meta = await response.json();
  if (state.ws) { const ws = state.ws; state.ws = null; ws.close(); }
  clearInterval(state.pollTimer);
  Object.assign(state, { doc, bounds: meta.bounds, version: meta.version, requested: null, answered: null,
                         truncated: false, transport: "ws", cells: [] });  // prettier-ignore
  state.held.clear();
  state.sentAt.clear();
  heldChanged();
  history.replaceState(null, "", `?doc=${doc}${TOKEN ? `&token=${encodeURIComponent(TOKEN)}` : ""}`);
  $("doc").value = doc;
  fit(false);
  connect();
}

async function start() {
  POLICY = await (await fetch("/static/policy.json")).json();
  const docs = await (await api("/documents")).json();
  const select = $("doc");
  for (const d of docs) select.add(new Option(`${d.name} (${d.items.toLocaleString()} items)`, d.id));
  const wanted = new URLSearchParams(location.search).get("doc");
  const first = docs.find((d) => d.id === wanted) || docs.find((d) => /report/i.test(d.name)) || docs[0];
  if (first) await open(first.id);
  else showError("no documents yet: run `vantage demo`, or import one");
  requestAnimationFrame(draw);
}

// For tests and the console: what the page holds, and whether it matches what it asked for.
window.vantage = {
  state: () => ({
    doc: state.doc, version: state.version, transport: state.transport,
    synced: !!state.requested && state.done === state.requested.seq && !needsRequest() && !state.busy,
    covered: !!state.answered && !state.truncated && inside(screenRect(), state.answered.rect),  // no blank edge
    requested: state.requested && { rect: state.requested.rect, scale: state.requested.scale, minPx: POLICY.minPx },
    band: state.answered ? state.answered.band ?? null : null,  // the zoom band of the held aggregates
    viewport: screenRect(), scale: state.cam.scale, truncated: state.truncated, held: [...state.held.keys()],
    // The canvas shows a frame drawn from this very camera and held set (not an older one):
    drawn: isDrawn(), painted: state.painted && { ...state.painted }, generation: state.generation,
    goto: { ...state.goto, last: state.goto.last && { ...state.goto.last } },
  }),
  items: () => [...state.held.values()],
  useHttp,
  centreOn, zoomAt, goTo,
};

start();
