// Vantage canvas: pan and zoom a document the server holds, keeping only what is near the screen.
//
// Every frame is drawn from the client's local item set; the network only feeds that set. All
// talk with the server (the stream, HTTP diffs, reconnecting, the fetch policy, "go to"'s
// lookups) is in vantage-client.js, the module another canvas app imports too: this page only
// tells it where the screen is, each frame, and draws what it holds. Zoomed out, the aggregates
// standing in for items too small to draw come in tiles fixed in canvas space, which the client
// keeps across pans and zooms; the page draws them at the scales of their ladder, where each of
// their bits is a screen pixel (between scales, each bit inks every pixel it touches).
import { TilePainter, VantageClient, inside, maskImage, onLadder } from "./vantage-client.js";

const COLOURS = {            // fill, stroke by kind
  page: ["#ffffff", "#b9bec8"], text: ["#5b6270", null], image: ["#8fb3d9", null],
  note: ["#ffd866", "#d9a800"], frame: [null, "#7a5cff"], box: ["#5aa469", null],
};
const HIGHLIGHT = "#e8336e";   // the outline around a "go to"'s target
const INK = "#1f2430";         // an item's text (its data.text), once it is big enough to read
const TEXT_MIN_PX = 8;         // drawn when its box is at least this tall on screen,
const TEXT_MOST = 800;         // and no more than this many texts are in view (else the bars: text costs)
const TEXT_FONT = "system-ui, sans-serif";
const WORD_EM = 0.85;          // a word's font size, in its box's heights (a font's line is ~1.2 em)
const HIGHLIGHT_MS = 4000;     // for this long
const FOUND = "rgba(255, 200, 0, 0.45)";  // every hit of the find box, over its items
const FIND_DEBOUNCE_MS = 200;  // the find box searches once typing pauses this long
const FIND_PAGE = 1000;        // hits fetched a page at a time

const $ = (id) => document.getElementById(id);
// When reads need a token, open the page as /#token=... (a fragment never reaches a server's log;
// ?token= works too): the client sends it as a header, and in the stream's URL (a browser cannot
// set a WebSocket's headers).
const TOKEN = new URLSearchParams(location.hash.slice(1)).get("token") || new URLSearchParams(location.search).get("token");
const canvas = $("canvas"), ctx = canvas.getContext("2d");
const client = new VantageClient({ token: TOKEN, tiles: true, onStatus: (s) => { if (s.error && !s.reconnecting) showError(s.error); } });
const painter = new TilePainter();

const state = {
  doc: null, bounds: null,
  cam: { x: 0, y: 0, scale: 1 },      // the canvas point at the screen's top-left; pixels per unit (see view())
  anchor: null,                       // the pixel the last zoom was around (null: the screen's centre)
  order: [], orderOf: -1,             // the client's items by z, and the generation they are of
  tiles: [], layers: [], standing: [],  // zoomed out: the tiles held, their kinds by z, their aggregates
  painted: null,                      // what the last frame was drawn from: see draw()
  goto: { started: 0, done: 0, pending: 0, last: null },  // "go to"s: counts, and how the last one ended
  highlight: null,                    // { id, box, until }: a "go to"'s target, outlined for a while
  find: { q: "", hits: [], at: -1, total: 0, next: null, seq: 0 },  // the find box's hits, and the current one
  marks: 0,                           // bumped when the highlight appears or goes
  fps: 0, frames: [],
  cells: [], showCells: false, cellsAt: 0,
};

// -- geometry --------------------------------------------------------------------------

function view() {
  // What the screen shows: the camera; zoomed out with tiles, the camera at the tiles' ladder
  // scale at or below its own, about the last zoom's pixel, its corner on a whole pixel (a tile
  // bit a pixel). Zooms around a point keep that point where it is, on the ladder and off it.
  if (!client.zoomedOut) return state.cam;
  return onLadder(state.cam, state.anchor || [canvas.clientWidth / 2, canvas.clientHeight / 2]);
}

function screenRect() {
  const { x, y, scale } = view();
  return [x, y, x + canvas.clientWidth / scale, y + canvas.clientHeight / scale];
}

// -- the camera ------------------------------------------------------------------------

function panBy(dxPx, dyPx) {
  const { scale } = view();  // the content follows the pointer pixel for pixel
  state.cam.x += dxPx / scale;  // float64 throughout: no drift far from the origin
  state.cam.y += dyPx / scale;
}

function zoomAt(px, py, factor) {
  // The canvas point under (px, py) stays there (to within half a pixel, on the ladder).
  const { cam } = state, before = view();
  const ux = before.x + px / before.scale, uy = before.y + py / before.scale;
  cam.scale = Math.min(1e6, Math.max(1e-12, cam.scale * factor));
  cam.x = ux - px / cam.scale;
  cam.y = uy - py / cam.scale;
  state.anchor = [px, py];
}

function centreOn(x, y, scale = state.cam.scale) {
  state.anchor = null;
  state.cam.scale = scale;
  state.cam.x = x - canvas.clientWidth / 2 / scale;
  state.cam.y = y - canvas.clientHeight / 2 / scale;
}

function fit(wholeDocument) {
  const b = state.bounds;
  if (!b) return centreOn(0, 0, 1);
  const w = Math.max(b[2] - b[0], 1e-9), h = Math.max(b[3] - b[1], 1e-9);
  const W = canvas.clientWidth, H = canvas.clientHeight;
  state.anchor = null;
  if (!wholeDocument && h > 4 * w) {  // a long document: its width on screen, from the top
    const scale = Math.min(W / w, 2) * 0.95;
    state.cam.scale = scale;
    state.cam.x = (b[0] + b[2]) / 2 - W / 2 / scale;
    state.cam.y = b[1] - 10 / scale;
  } else {
    centreOn((b[0] + b[2]) / 2, (b[1] + b[3]) / 2, Math.min(W / w, H / h) * 0.95);
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
  client.view(screenRect(), view().scale, now);  // asks the server for more if the policy says so
  const generation = client.generation;
  if (state.orderOf !== generation) {
    state.tiles = client.tiles();
    state.layers = client.layerOrder(state.tiles, Object.keys(COLOURS));
    state.standing = client.tileAggregates(state.tiles);
    const boxed = state.standing.filter((a) => a.boxed);  // no bits: drawn as their box, among the items
    state.order = [...boxed, ...client.items.values()].sort((a, b) => (a.z ?? 0) - (b.z ?? 0));
    state.orderOf = generation;  // `order` is the items (and tiles) as of this generation
  }
  if (state.highlight && now > state.highlight.until) {
    state.highlight = null;
    state.marks++;
  }
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.fillStyle = "#e9ebee";
  ctx.fillRect(0, 0, W, H);
  const { x, y, scale } = view();
  const texts = readableTexts(W, H);  // draw texts this frame, or (too many, or none) only boxes
  let shown = 0, standing = 0, font = "", layer = 0;
  painter.frame(now);
  for (const item of state.order) {
    // The tiles' layers go in by z too, under the items of their z (as aggregates came first).
    while (layer < state.layers.length && state.layers[layer].z <= (item.z ?? 0)) drawLayer(state.layers[layer++].kind);
    // Subtract in float64 first, then scale: only small numbers reach the canvas.
    const sx = (item.x0 - x) * scale, sy = (item.y0 - y) * scale;
    const sw = Math.max((item.x1 - item.x0) * scale, 1), sh = Math.max((item.y1 - item.y0) * scale, 1);
    if (sx > W || sy > H || sx + sw < 0 || sy + sh < 0) continue;
    shown++;
    const [fill, stroke] = COLOURS[item.kind] || COLOURS.box;
    if (item.agg) {  // stands in for items too small to draw: the pixels they cover, in their kind
      standing += item.agg.count;
      const m = item.mask;
      if (m) {
        ctx.imageSmoothingEnabled = false;  // a cell is a pixel: drawn sharp, as the items would be
        ctx.drawImage(maskImage(item, fill || stroke), (m.x0 - x) * scale, (m.y0 - y) * scale,
                      m.w * m.cell * scale, m.h * m.cell * scale);
        continue;
      }
      ctx.globalAlpha = 0.35 + 0.65 * item.agg.cover;  // no mask (a huge one): as dense as they cover its box
      ctx.fillStyle = fill || stroke;
      ctx.fillRect(sx, sy, sw, sh);
      ctx.globalAlpha = 1;
      continue;
    }
    const text = texts && sh >= TEXT_MIN_PX ? textOf(item) : null;
    if (fill && !(text && item.kind === "text")) {  // a word big enough to read is its text, not a bar
      ctx.fillStyle = fill;
      if (item.kind === "text") ctx.fillRect(sx, sy + sh * 0.2, sw, Math.max(sh * 0.6, 1));
      else ctx.fillRect(sx, sy, sw, sh);
    }
    if (stroke && sw > 3 && sh > 3) {
      ctx.strokeStyle = stroke;
      ctx.strokeRect(sx + 0.5, sy + 0.5, sw - 1, sh - 1);
    }
    if (text) font = drawText(text, sx, sy, sw, sh, font, item.kind === "text" && !text.includes("\n"));
  }
  while (layer < state.layers.length) drawLayer(state.layers[layer++].kind);
  for (const agg of state.standing) {  // what the tiles' layers show, counted
    if (agg.boxed || agg.x0 - x > W / scale || agg.y0 - y > H / scale || agg.x1 < x || agg.y1 < y) continue;
    shown++;
    standing += agg.agg.count;
  }
  if (state.showCells) drawCells();
  drawFound(W, H);
  if (state.highlight) for (const box of state.highlight.boxes) drawHighlight(box);
  // Complete: every tile the answer names is held, and drawn exactly (none stretched meanwhile).
  const complete = client.tilesComplete && painter.exact;
  painted({ x, y, scale, generation, marks: state.marks, width: W, height: H, dpr, complete });
  state.frames.push(now);
  while (state.frames.length && now - state.frames[0] > 1000) state.frames.shift();
  status(shown, standing);
  requestAnimationFrame(draw);
}

function drawLayer(kind) {
  // One kind's bits in every tile held, in the colour its aggregates are drawn in.
  const [fill, stroke] = COLOURS[kind] || COLOURS.box, { x, y, scale } = view();
  for (const tile of state.tiles) painter.draw(ctx, tile, kind, fill || stroke, x, y, scale);
}

function textOf(item) {
  const text = item.data && item.data.text;
  return typeof text === "string" && text && !item.agg ? text : null;
}

function readableTexts(W, H) {
  // Whether this frame draws items' text: some item with text is tall enough on screen to read,
  // and at most TEXT_MOST are (past that, text would cost more than a frame has, and be a blur).
  const { x, y, scale } = view();
  if (!state.order.length) return false;
  let count = 0;
  for (const item of state.order) {
    if ((item.y1 - item.y0) * scale < TEXT_MIN_PX || !textOf(item)) continue;
    const sx = (item.x0 - x) * scale, sy = (item.y0 - y) * scale;
    if (sx > W || sy > H || sx + (item.x1 - item.x0) * scale < 0 || sy + (item.y1 - item.y0) * scale < 0) continue;
    if (++count > TEXT_MOST) return false;
  }
  return count > 0;
}

function drawText(text, sx, sy, sw, sh, font, word) {
  // The text in its box, clipped to it. A word, or a line (kind "text" on one line: a box the
  // font's line tall, where a document draws it), is drawn at the size its box's height gives, narrowed or widened to span
  // its box: the words of a line, as tall as one another, are drawn at one size, each where it
  // is. Other items' text is as tall as the box allows, narrowed to its width down to 6 px (then
  // cut at the box's edge). Returns the font now set.
  let size = Math.min(sh * (word ? WORD_EM : 0.8), 200);
  const wanted = `${size.toFixed(1)}px ${TEXT_FONT}`;
  if (wanted !== font) ctx.font = font = wanted;
  const width = ctx.measureText(text).width;
  if (!word && width > sw) {
    size = Math.max(6, size * sw / width);
    ctx.font = font = `${size.toFixed(1)}px ${TEXT_FONT}`;
  }
  ctx.save();
  ctx.beginPath();
  ctx.rect(sx, sy, sw, sh);
  ctx.clip();
  ctx.fillStyle = INK;
  ctx.textBaseline = "middle";
  if (word && width > 0) {
    ctx.translate(sx, 0);
    ctx.scale(sw / width, 1);
    ctx.fillText(text, 0, sy + sh / 2);
  } else {
    ctx.fillText(text, sx, sy + sh / 2);
  }
  ctx.restore();
  return font;
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
    a.marks === b.marks && a.width === b.width && a.height === b.height && a.dpr === b.dpr && a.complete === b.complete;
}

function isDrawn() {
  // Whether the canvas shows the current camera over the current held set (and all its tiles),
  // at its current size.
  const { x, y, scale } = view();
  const now = { x, y, scale, generation: client.generation, marks: state.marks, ...canvasSize(), complete: true };
  return !!state.painted && sameFrame(state.painted, now);
}

function drawCells() {
  const { x, y, scale } = view();
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
    client.cells(r).then((body) => { state.cells = body.cells || []; }, () => {});
  }
}

function drawFound(W, H) {
  // Every hit of the find box on screen, filled over its items, in canvas units: it stays on
  // what it marks as the camera pans and zooms.
  const { x, y, scale } = view();
  ctx.fillStyle = FOUND;
  // A box each line a hit covers (a phrase that wraps is marked on each line, not as one
  // block over both); a server without `boxes` gives the one `box`.
  for (const hit of state.find.hits) for (const [x0, y0, x1, y1] of hit.boxes || [hit.box]) {
    const sx = (x0 - x) * scale, sy = (y0 - y) * scale;
    const sw = Math.max((x1 - x0) * scale, 2), sh = Math.max((y1 - y0) * scale, 2);
    if (sx > W || sy > H || sx + sw < 0 || sy + sh < 0) continue;
    ctx.fillRect(sx - 1, sy - 1, sw + 2, sh + 2);
  }
}

function drawHighlight([x0, y0, x1, y1]) {
  // An outline 4 px outside the target's box (a ring around a point), drawn the same every
  // frame until it goes: a frame's picture is still its camera, items and marks.
  const { x, y, scale } = view();
  const sx = (x0 - x) * scale, sy = (y0 - y) * scale;
  const sw = (x1 - x0) * scale, sh = (y1 - y0) * scale;
  ctx.lineWidth = 3;
  ctx.strokeStyle = HIGHLIGHT;
  ctx.beginPath();
  if (sw < 2 && sh < 2) ctx.arc(sx + sw / 2, sy + sh / 2, 12, 0, 2 * Math.PI);
  else ctx.rect(sx - 4, sy - 4, sw + 8, sh + 8);
  ctx.stroke();
  ctx.lineWidth = 1;
}

let errorUntil = 0;
// Shown for 4 s, or until a document opens when `sticky` (nothing the page does next can fix it).
function showError(message, sticky = false) {
  errorUntil = sticky ? Infinity : performance.now() + 4000;
  $("status").textContent = message;
  $("status").className = "warn";
}

function connection() {
  if (client.reconnecting) return "server unreachable: reconnecting";
  if (client.live) return "live (stream)";
  if (client.transport === "http") return client.zoomedOut && !client.forcedHttp ? "polling (zoomed out: tiles)" : "polling";
  if (client.transport === "none") return "offline";
  return "connecting";
}

function status(shown, standing) {
  if (performance.now() < errorUntil) return;
  const el = $("status");
  el.className = client.truncated || client.reconnecting ? "warn" : "";
  const grouped = standing ? ` (${standing.toLocaleString()} too small to draw, shown grouped)` : "";
  const tiles = client.sheet ? ` · ${state.tiles.length} tiles` : "";
  el.textContent = `${shown.toLocaleString()} items in view${grouped} · ${client.items.size.toLocaleString()} loaded` +
    `${client.truncated ? " (truncated: zoom in)" : ""}${tiles} · last change ${client.lastDiff} · ` +
    `${client.rtt.toFixed(0)} ms · ${state.frames.length} fps · version ${client.version} · ${connection()}`;
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
let findTimer = null;
$("find").addEventListener("input", () => {  // as you type, once typing pauses
  clearTimeout(findTimer);
  findTimer = setTimeout(() => find($("find").value), FIND_DEBOUNCE_MS);
});
$("find").addEventListener("keydown", (e) => {
  if (e.key !== "Enter") return;
  e.preventDefault();
  clearTimeout(findTimer);
  if ($("find").value.trim() !== state.find.q) find($("find").value);  // typed, then Enter at once
  else step(e.shiftKey ? -1 : 1);
});

async function find(text) {
  // Every hit of `text` (a page of FIND_PAGE; more as Enter reaches them), highlighted; the
  // first one shown. A newer search, or another document, drops this one's answer.
  const q = text.trim(), seq = ++state.find.seq, doc = state.doc;
  if (!q) {
    Object.assign(state.find, { q, hits: [], at: -1, total: 0, next: null });
    $("find-count").textContent = "";
    return state.marks++;
  }
  try {
    const page = await client.search(q, { limit: FIND_PAGE });
    if (seq !== state.find.seq || doc !== state.doc) return;
    Object.assign(state.find, { q, hits: page.hits, at: -1, total: page.total, totalExact: page.total_exact,
                                next: page.next || null });  // prettier-ignore
    if (page.hits.length) step(1);
    else $("find-count").textContent = "no match";
    state.marks++;
  } catch (error) {
    if (seq === state.find.seq) showError(String(error.message || error));
  }
}

async function step(by) {
  // Enter: the next hit, Shift+Enter: the one before (round the ends), shown and outlined.
  const f = state.find;
  if (!f.hits.length) return;
  if (by > 0 && f.at + 1 >= f.hits.length && f.next) {  // the next page of hits, when Enter gets there
    const page = await f.next();
    f.hits = f.hits.concat(page.hits);
    f.next = page.next || null;
  }
  f.at = (f.at + by + f.hits.length) % f.hits.length;
  const hit = f.hits[f.at], [x0, y0, x1, y1] = hit.box;
  const size = Math.max(x1 - x0, y1 - y0, 1e-9);
  const readable = Math.min(canvas.clientWidth, canvas.clientHeight) / 3 / size;
  centreOn((x0 + x1) / 2, (y0 + y1) / 2, Math.min(readable, Math.max(state.cam.scale, readable / 8)));
  mark(hit.ids[0], hit.box, hit.boxes);
  $("find-count").textContent = `${f.at + 1} of ${f.total}${f.totalExact ? "" : "+"}`;
}


// Two numbers, as JavaScript writes them ("1e400" is one too, and not finite).
const NUMBER = String.raw`[-+]?(?:\d+\.?\d*|\.\d+)(?:e[-+]?\d+)?`;
const COORDS = new RegExp(String.raw`^\s*(${NUMBER})\s*(?:,\s*|\s+)(${NUMBER})\s*$`, "i");

async function goTo(text) {
  // Centre on "x, y"; on an item by id; else on the first item whose text holds every word.
  // Items are fetched first: the camera moves when they arrive. `state.goto` counts them, so a
  // test or the console can tell when the camera has moved; the target is outlined for a while.
  const { goto } = state, seq = ++goto.started, doc = state.doc;
  const current = () => seq === goto.started && doc === state.doc;
  goto.pending++;
  let outcome = "superseded";  // by a later "go to" or another document: this one moves nothing
  try {
    text = String(text ?? "").trim();
    if (!text) {
      outcome = "empty";
      return showError("go to takes x, y (two numbers), an item id, or words to find");
    }
    const coords = text.match(COORDS);
    if (coords) {
      const x = Number(coords[1]), y = Number(coords[2]), w = canvas.clientWidth, h = canvas.clientHeight;
      const s = state.cam.scale;
      if (![x, y, x - w / s, y - h / s, x + w / s, y + h / s].every(Number.isFinite)) {
        outcome = "invalid";
        return showError(`the coordinates must be finite numbers (not ${text})`);
      }
      centreOn(x, y);
      mark(null, [x, y, x, y]);
      outcome = "moved";
      return;
    }
    let item = await client.item(text);
    if (!current()) return;
    if (!item) {
      const found = await client.search(text, 20).catch((error) => {
        if (error.status === 404) return { items: [] };  // a server without search
        throw error;
      });
      if (!current()) return;
      item = found.items[0];
      if (!item) {
        outcome = "not found";
        return showError(`no item or text matching ${JSON.stringify(text)}`);
      }
    }
    const size = Math.max(item.x1 - item.x0, item.y1 - item.y0, 1e-9);
    const readable = Math.min(canvas.clientWidth, canvas.clientHeight) / 3 / size;  // a third of the screen
    const scale = Math.min(readable, Math.max(state.cam.scale, readable / 8));  // zoom only as far as needed
    centreOn((item.x0 + item.x1) / 2, (item.y0 + item.y1) / 2, scale);
    mark(item.id, [item.x0, item.y0, item.x1, item.y1]);
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

function mark(id, box, boxes = [box]) {
  state.highlight = { id, box, boxes, until: performance.now() + HIGHLIGHT_MS };
  state.marks++;
}

// -- start -------------------------------------------------------------------------------

// A refusal (401, 403) in the server's words, told apart from a server that cannot be reached.
function refused(error) {
  if (error.status !== 401 && error.status !== 403) return null;
  const who = TOKEN ? "the token" : "the page without a token (open it as /#token=…)";
  return `the server refused ${who} (${error.status}): ${error.message}`;
}

async function open(doc) {
  let meta;
  try {
    meta = await client.open(doc);
  } catch (error) {
    if (error.status === 404) return showError(`document ${doc} not found`, true);
    return showError(refused(error) || String(error.message || error), !!refused(error));
  }
  errorUntil = 0;
  Object.assign(state, { doc, bounds: meta.bounds, cells: [], highlight: null });
  Object.assign(state.find, { q: "", hits: [], at: -1, total: 0, next: null });
  $("find").value = $("find-count").textContent = "";
  state.marks++;
  history.replaceState(null, "", `?doc=${doc}${TOKEN ? `#token=${encodeURIComponent(TOKEN)}` : ""}`);
  $("doc").value = doc;
  fit(false);
  // Told before the first frame: a first view that looks zoomed out (a big document at Fit) is
  // asked tiled from the start, and that frame is drawn on the tiles' ladder already.
  client.firstView(screenRect(), view().scale);
}

async function start() {
  let docs;
  try {
    await client.ready();  // the fetch policy, static/policy.json
    docs = await client.documents();
  } catch (error) {
    return showError(refused(error) || `the server cannot be reached (${error.message || error}): reload to try again`, true);
  }
  const select = $("doc");
  for (const d of docs) select.add(new Option(`${d.name} (${d.items.toLocaleString()} items)`, d.id));
  const wanted = new URLSearchParams(location.search).get("doc");
  // The document asked for is opened even when the list leaves it out (a token lists only what it
  // grants): its refusal says which document, never another document shown in its place.
  const first = wanted || (docs.find((d) => /report/i.test(d.name)) || docs[0] || {}).id;
  if (first) await open(first);
  else showError("no documents yet: run `vantage demo`, or import one");
  if (!state.doc) select.selectedIndex = -1;  // none open: any choice is a change
  requestAnimationFrame(draw);
}

// For tests and the console: what the page holds, and whether it matches what it asked for.
window.vantage = {
  state: () => {
    const screen = screenRect(), drawn = view(), req = client.requested, answered = client.answered;
    return {
      doc: state.doc, version: client.version, transport: client.transport, live: client.live,
      reconnecting: client.reconnecting, synced: client.synced(screen, drawn.scale),
      covered: !!answered && !client.truncated && inside(screen, answered.rect),  // no blank edge
      requested: req && { rect: req.rect, scale: req.scale, minPx: client.policy.minPx },
      band: client.band,  // the zoom band of the held aggregates
      // Zoomed out: the tiles the answer names, those near the screen (fetched and drawn), those
      // held, and their aggregates' ids.
      tiles: client.sheet && { ...client.sheet, range: [...client.sheet.range] },
      tilesNear: client.tileRange && [...client.tileRange], told: client.screen && [...client.screen],  // the screen it aims at
      tilesHeld: client.tiles().map((t) => t.path), tileFetches: client.tileFetches,
      aggregates: client.tileAggregates().map((a) => a.id),
      viewport: screen, scale: drawn.scale, truncated: client.truncated, held: [...client.items.keys()],
      // The canvas shows a frame drawn from this very camera, held set and highlight (not an older one):
      drawn: isDrawn(), painted: state.painted && { ...state.painted }, generation: client.generation,
      goto: { ...state.goto, last: state.goto.last && { ...state.goto.last } },
      highlight: state.highlight && {
        id: state.highlight.id, box: [...state.highlight.box], boxes: state.highlight.boxes.map((b) => [...b]),
      },
      find: { q: state.find.q, hits: state.find.hits.length, at: state.find.at, total: state.find.total,
              count: $("find-count").textContent },  // prettier-ignore
      status: $("status").textContent,
    };
  },
  items: () => [...client.items.values()],
  useHttp: () => client.useHttp(),
  client, centreOn, zoomAt, goTo,
};

start();
