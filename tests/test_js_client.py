"""static/vantage-client.js, the module another canvas app imports, in a real browser (Debian's
Chromium) against real server processes: a tiny page of its own holds what brute force shows as
it pans; zoomed out with tiles, it decodes and draws their bits as the server set them, and a
first view zoomed out is asked tiled from the start; the demo
page rides out a server restart (keeps its picture, says it is reconnecting, goes back to the
stream and shows edits made after); and the page's "go to" fixes."""

import base64
import os
import subprocess
import sys

import httpx
import numpy as np
import orjson
import pytest
from browser import artifact, chromium_page
from PIL import Image
from service import ndjson, serving
from test_browser import TEXT, _check_held, _drawn, _import, _shot, _synced, _tile_bits, _touched

from app.access import mint
from app.launch import launch, wait_until_up
from spatial import scenes

HIGHLIGHT = (0xE8, 0x33, 0x6E)  # the page's outline around a "go to"'s target

# A canvas app of its own: the client, a camera, a draw loop, and the state _check_held reads.
TINY = """<!doctype html>
<canvas id="c" width="800" height="600"></canvas>
<script type="module">
import { VantageClient } from "/static/vantage-client.js";
const doc = new URLSearchParams(location.search).get("doc");
const client = new VantageClient({ doc });
const cam = { x: 0, y: 0, scale: 1.5 }, W = 800, H = 600;
const screen = () => [cam.x, cam.y, cam.x + W / cam.scale, cam.y + H / cam.scale];
const ctx = document.getElementById("c").getContext("2d");
let changes = 0;
client.onChange = () => changes++;
function frame(now) {
  client.view(screen(), cam.scale, now);
  ctx.clearRect(0, 0, W, H);
  for (const it of client.items.values())
    ctx.fillRect((it.x0 - cam.x) * cam.scale, (it.y0 - cam.y) * cam.scale,
                 (it.x1 - it.x0) * cam.scale, (it.y1 - it.y0) * cam.scale);
  requestAnimationFrame(frame);
}
await client.open();
window.vantage = {
  pan: (dx, dy) => { cam.x += dx / cam.scale; cam.y += dy / cam.scale; },
  zoom: (f) => { cam.scale *= f; },
  useHttp: () => client.useHttp(),
  client,
  state: () => ({
    synced: client.synced(screen(), cam.scale), transport: client.transport, live: client.live,
    requested: client.requested && { rect: client.requested.rect, scale: client.requested.scale,
                                     minPx: client.policy.minPx },
    band: client.band, held: [...client.items.keys()], truncated: client.truncated,
    viewport: screen(), scale: cam.scale, changes,
  }),
};
requestAnimationFrame(frame);
</script>
"""


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A served store with a 12-page document whose words carry text: ``(url, doc, boxes)``."""
    boxes, kinds = scenes.long_document(pages=12, seed=7)
    with serving(tmp_path_factory.mktemp("js-client-data")) as url:
        doc = _import(url, "report", ndjson(boxes, kinds))
        yield url, doc, boxes


def _with(page_text: str, old: str, new: str) -> str:
    """``page_text`` with ``old`` (which must be there: else the page is silently unchanged) as ``new``."""
    assert page_text.count(old) == 1, f"{old!r} is not in the page once"
    return page_text.replace(old, new)


def _tiny(page, url: str, doc: str, content: str = TINY) -> None:
    # Written into a page the server answered, so Chromium's local network access checks let
    # its WebSocket through (they block one from a page Playwright made up).
    page.goto(f"{url}/health?doc={doc}")
    page.set_content(content)


def test_a_canvas_app_of_its_own_holds_what_brute_force_shows(site):
    url, doc, boxes = site
    with chromium_page() as page:
        _tiny(page, url, doc)
        first = _check_held(page, url, doc, boxes)
        assert first["transport"] == "ws" and first["live"] and len(first["held"]) > 50
        for dx, dy in ((300, 900), (0, 2500), (-200, 4000), (0, -1500)):
            page.evaluate(f"() => window.vantage.pan({dx}, {dy})")
            _check_held(page, url, doc, boxes)
        for factor in (0.25, 0.25, 0.5, 8):  # through the levels of detail and back
            page.evaluate(f"() => window.vantage.zoom({factor})")
            state = _check_held(page, url, doc, boxes)
        assert state["changes"] > 5


def test_over_http_the_client_keeps_the_same_set(site):
    url, doc, boxes = site
    with chromium_page() as page:
        _tiny(page, url, doc)
        _check_held(page, url, doc, boxes)
        page.evaluate("() => window.vantage.useHttp()")
        for dx, dy, factor in ((0, 3000, 1), (100, 0, 0.25), (0, 800, 0.5), (0, 0, 8)):
            page.evaluate(f"() => {{ window.vantage.pan({dx}, {dy}); window.vantage.zoom({factor}); }}")
            state = _check_held(page, url, doc, boxes)
            assert state["transport"] == "http" and not state["live"]


# Each of (up to) four tiles the client holds, each kind's layer drawn by a TilePainter on a
# canvas of its own, for each case: at the tile's scale times k, its corner at (1 + ox, 1 + oy)
# pixels. The pixels inked, one byte each, base64.
DRAW_TILES = """async (cases) => {
  const { TilePainter } = await import("/static/vantage-client.js");
  const painter = new TilePainter({ renderMs: Infinity }), out = [];  // every layer drawn exactly
  const base64 = (bytes) => {
    let text = "";
    for (let i = 0; i < bytes.length; i += 8192) text += String.fromCharCode(...bytes.subarray(i, i + 8192));
    return btoa(text);
  };
  for (const tile of window.vantage.client.tiles().filter((t) => t.layers.size).slice(0, 4)) {
    const kinds = {};
    for (const kind of tile.layers.keys()) {
      kinds[kind] = cases.map(([k, ox, oy]) => {
        const w = Math.ceil(tile.size * k) + 3, scale = tile.scale * k;
        const ctx = new OffscreenCanvas(w, w).getContext("2d");
        painter.frame();
        painter.draw(ctx, tile, kind, "#123456", tile.box[0] - (1 + ox) / scale, tile.box[1] - (1 + oy) / scale, scale);
        const rgba = ctx.getImageData(0, 0, w, w).data, inked = new Uint8Array(w * w);
        for (let i = 0; i < w * w; i++) inked[i] = rgba[4 * i + 3] === 255 ? 1 : 0;
        return { w, inked: base64(inked) };
      });
    }
    out.push({ path: tile.path, kinds });
  }
  return out;
}"""


def test_zoomed_out_the_client_decodes_tiles_as_the_server_set_them_and_a_bit_inks_every_pixel_it_touches(
    site,
):
    """vantage-client.js with ``tiles: true``, zoomed out, fetches the tiles its answers name, and
    decodes each layer (base64, zlib, bits least significant first, row by row) into the bits
    Python reads from the same tile: drawn at the tile's own scale, a pixel a bit. At other scales
    and offsets within a pixel, each set bit inks every pixel it touches and no other, a bit
    smaller than a pixel too (brute force)."""
    url, doc, _ = site
    cases = [(1.0, 0.0, 0.0), (0.7, 0.3, 0.55), (0.26, 0.9, 0.1), (2.5, 0.25, 0.5)]
    with chromium_page() as page:
        _tiny(page, url, doc)
        page.set_content(_with(TINY, "new VantageClient({ doc })", "new VantageClient({ doc, tiles: true })"))
        page.wait_for_function("() => window.vantage && window.vantage.state().synced", timeout=15_000)
        page.evaluate("() => window.vantage.zoom(0.03)")  # aggregates of words, on pages
        page.wait_for_function(
            """() => { const c = window.vantage.client;
                       return window.vantage.state().synced && !!c.sheet && c.tilesComplete
                         && c.tiles().some((t) => t.layers.size); }""",
            timeout=60_000,  # the document's first tiles are made now: on a busy machine, seconds
        )
        state = page.evaluate("() => window.vantage.state()")
        drawn = page.evaluate(DRAW_TILES, cases)
    assert state["transport"] == "http" and not any(i.startswith("~") for i in state["held"])
    assert drawn
    for tile in drawn:
        body, layers = _tile_bits(url, tile["path"])
        assert set(tile["kinds"]) == set(layers)
        n = body["size"]
        for kind, shots in tile["kinds"].items():
            rows, cols = np.nonzero(layers[kind])
            assert len(rows), f"{tile['path']}: an empty {kind} layer"
            bits = np.column_stack([cols, rows, cols + 1, rows + 1]).astype(float)  # in the tile's pixels
            for (k, ox, oy), shot in zip(cases, shots, strict=True):
                w = shot["w"]
                inked = np.frombuffer(base64.b64decode(shot["inked"]), np.uint8).reshape(w, w).astype(bool)
                view = (-(1 + ox) / k, -(1 + oy) / k, k)
                inner, outer = _touched(bits, view, (w, w), -1e-6), _touched(bits, view, (w, w), 1e-6)
                where = f"{tile['path']} {kind} at {k}x, offset ({ox}, {oy})"
                assert (inner <= inked).all(), (
                    f"{where}: {(inner & ~inked).sum()} pixels a set bit touches not inked"
                )
                assert (inked <= outer).all(), (
                    f"{where}: {(inked & ~outer).sum()} pixels inked no set bit touches"
                )
            one = np.frombuffer(base64.b64decode(shots[0]["inked"]), np.uint8).reshape(shots[0]["w"], -1)
            assert (one[1 : n + 1, 1 : n + 1].astype(bool) == layers[kind]).all()  # a pixel a bit, exactly
            assert one.sum() == len(rows)


def test_a_tiled_client_whose_first_view_is_zoomed_out_asks_it_tiled_from_the_first_request(site):
    """With ``tiles: true``, a first view() showing the whole report small (its words under a
    pixel) is asked tiled over HTTP from the start: no stream opens to answer aggregates and
    their masks first, and the tiles the answer names near the screen are fetched and held."""
    url, doc, _ = site
    tiled = _with(TINY, "new VantageClient({ doc })", "new VantageClient({ doc, tiles: true })")
    with chromium_page() as page:
        page.goto(f"{url}/health?doc={doc}")
        asked, streams = [], []
        page.on("request", lambda request: asked.append(request.url))
        page.on("websocket", lambda ws: streams.append(ws.url))
        page.set_content(_with(tiled, "scale: 1.5", "scale: 0.03"))
        page.wait_for_function(
            """() => { const c = window.vantage && window.vantage.client;
                       return !!c && window.vantage.state().synced && !!c.sheet && c.tilesComplete
                         && c.tiles().length > 0; }""",
            timeout=15_000,
        )
        state = page.evaluate("() => window.vantage.state()")
        zoomed_out = page.evaluate("() => window.vantage.client.zoomedOut")
    views = [u for u in asked if "/viewport?" in u or "/diff?" in u]
    assert not streams, "a stream opened for a first view zoomed out"
    assert views and "/viewport?" in views[0] and all("tiles=true" in u for u in views)
    assert zoomed_out and state["transport"] == "http" and not any(i.startswith("~") for i in state["held"])


def _serve_on(port: int, data_dir) -> subprocess.Popen:
    """``vantage serve`` on ``port`` (the one a page was using), once it answers."""
    process = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "serve", "--port", str(port), "--workers", "1"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "VANTAGE_DATA_DIR": str(data_dir)},
    )
    try:
        wait_until_up(f"http://127.0.0.1:{port}", process, timeout=60)
    except RuntimeError:
        process.kill()
        raise
    return process


def _text_pixels(page, name: str) -> int:
    path = artifact(name)
    page.locator("canvas").screenshot(path=path)
    shot = np.asarray(Image.open(path).convert("RGB"))
    return int((shot.reshape(-1, 3) == TEXT).all(axis=1).sum())


def test_the_page_rides_out_a_server_restart_and_goes_back_live(tmp_path):
    boxes, kinds = scenes.long_document(pages=3, seed=5)
    server, url = launch(tmp_path, output=subprocess.DEVNULL)
    port = int(url.rsplit(":", 1)[1])
    again = None
    try:
        doc = _import(url, "report", ndjson(boxes, kinds))
        with chromium_page() as page:
            page.goto(f"{url}/?doc={doc}")
            before = _drawn(page, "(s) => s.live")
            assert "live (stream)" in before["status"]
            shown = _text_pixels(page, "client-before-restart.png")
            assert shown > 500

            server.terminate()
            server.wait(timeout=30)
            page.wait_for_function("() => window.vantage.state().reconnecting", timeout=15_000)
            page.wait_for_timeout(2500)  # past a poll and a few stream retries, all failing
            down = page.evaluate("() => window.vantage.state()")
            assert down["reconnecting"] and "reconnecting" in down["status"]
            assert "Failed to fetch" not in down["status"]
            assert sorted(down["held"]) == sorted(before["held"])  # the canvas keeps what it shows
            assert _text_pixels(page, "client-server-down.png") == shown

            again = _serve_on(port, tmp_path)
            back = _drawn(page, "(s) => s.live && !s.reconnecting", timeout=30_000)
            assert back["transport"] == "ws" and "live (stream)" in back["status"]

            x0, y0 = back["viewport"][:2]
            box = {"x0": x0 + 40, "y0": y0 + 40, "x1": x0 + 240, "y1": y0 + 140, "kind": "note", "z": 9}
            assert httpx.put(f"{url}/documents/{doc}/items/after-restart", json=box).status_code == 201
            page.wait_for_function(
                "() => window.vantage.state().held.includes('after-restart')", timeout=10_000
            )
            assert page.evaluate("() => window.vantage.state().live")
    finally:
        server.kill()
        if again is not None:
            again.terminate()
            again.wait(timeout=30)


def _go(page, text: str) -> dict:
    """Submit ``text`` in "go to"; the state once it is done and drawn."""
    before = page.evaluate("() => window.vantage.state().goto.done")
    page.fill("#goto", text)
    page.press("#goto", "Enter")
    return _drawn(page, f"(s) => s.goto.done > {before}")


def test_go_to_refuses_infinite_coordinates_and_says_what_it_takes_when_empty(site):
    url, doc, _ = site
    with chromium_page() as page:
        asked = []
        page.on("request", lambda request: asked.append(request.url))
        page.goto(f"{url}/?doc={doc}")
        start = _synced(page)

        state = _go(page, "1e400, 5")
        assert state["goto"]["last"]["outcome"] == "invalid"
        assert "must be finite numbers" in state["status"]
        assert state["viewport"] == start["viewport"] and state["highlight"] is None

        asked.clear()
        state = _go(page, "   ")
        assert state["goto"]["last"]["outcome"] == "empty"
        assert "go to takes x, y" in state["status"]
        assert not [u for u in asked if "/items" in u]  # no GET .../items/ (a 405)
        assert state["viewport"] == start["viewport"]

        state = _go(page, "-1e3 2e2")  # two numbers are coordinates: centred there
        assert state["goto"]["last"]["outcome"] == "moved"
        x0, y0, x1, y1 = state["viewport"]
        assert (x0 + x1) / 2 == pytest.approx(-1000) and (y0 + y1) / 2 == pytest.approx(200)
        assert state["highlight"]["box"] == [-1000, 200, -1000, 200]

        state = _go(page, "no such word zzqx")
        assert state["goto"]["last"]["outcome"] == "not found"
        assert 'no item or text matching "no such word zzqx"' in state["status"]


def test_go_to_outlines_its_target_for_a_few_seconds(site):
    url, doc, boxes = site
    target = 40
    with chromium_page() as page:
        page.goto(f"{url}/?doc={doc}")
        _synced(page)
        state = _go(page, f"i{target}")
        assert state["goto"]["last"]["outcome"] == "moved"
        assert state["highlight"]["id"] == f"i{target}"
        assert state["highlight"]["box"] == pytest.approx([float(v) for v in boxes[target]])
        _, shot = _shot(page, "client-highlight.png", "(s) => s.highlight !== null")
        outlined = int((shot.reshape(-1, 3) == HIGHLIGHT).all(axis=1).sum())
        assert outlined > 100
        gone, shot = _shot(page, "client-highlight-gone.png", "(s) => s.highlight === null")
        assert gone["viewport"] == state["viewport"]
        assert not (shot.reshape(-1, 3) == HIGHLIGHT).all(axis=1).any()


def test_go_to_words_finds_the_first_item_holding_them(tmp_path):
    """Words to go to are a phrase: the first hit's first item, a phrase across items too."""
    lines = [
        {
            "id": "a",
            "x0": 0,
            "y0": 0,
            "x1": 50,
            "y1": 10,
            "kind": "text",
            "data": {"text": "Quarterly revenue"},
        },
        {
            "id": "b",
            "x0": 0,
            "y0": 5000,
            "x1": 50,
            "y1": 5010,
            "kind": "text",
            "data": {"text": "Revenue by Region"},
        },
        {
            "id": "c",
            "x0": 0,
            "y0": 9000,
            "x1": 50,
            "y1": 9010,
            "kind": "text",
            "data": {"text": "region totals"},
        },
    ]
    body = b"".join(orjson.dumps(line) + b"\n" for line in lines)
    with serving(tmp_path) as url:
        doc = _import(url, "words", body)
        probe = httpx.get(f"{url}/documents/{doc}/search", params={"q": "region"})
        assert probe.status_code == 200, probe.text  # the page's "go to" words ask this route
        assert [i["id"] for i in probe.json()["items"]] == ["b", "c"]
        with chromium_page() as page:
            page.goto(f"{url}/?doc={doc}")
            _synced(page)
            state = _go(page, "by REGION")
            assert state["goto"]["last"]["outcome"] == "moved" and state["highlight"]["id"] == "b"
            _, y0, _, y1 = state["viewport"]
            assert (y0 + y1) / 2 == pytest.approx(5005)
            state = _go(page, "region REGION totals")  # the end of b, then c
            assert state["highlight"]["id"] == "b"
            state = _go(page, "revenue nowhere")
            assert state["goto"]["last"]["outcome"] == "not found"
            assert 'no item or text matching "revenue nowhere"' in state["status"]


def test_a_token_function_is_renewed_before_expiry_and_the_page_takes_a_fragment_token(tmp_path):
    """vantage-client.js with `token: () => fresh()`: called again a minute before each token
    expires (every ~3 s here), each fresh token sent on the stream, which stays live and
    answering; the page opened with `#token=` reads a document its signed token grants."""
    secret = "s" * 40
    boxes, kinds = scenes.long_document(pages=2, seed=3)
    env = {"VANTAGE_TOKENS": "backend", "VANTAGE_JWT_SECRET": secret}
    server, url = launch(tmp_path, env=env)
    try:
        backend = {"authorization": "Bearer backend"}
        doc = httpx.post(f"{url}/documents", json={"name": "r"}, headers=backend).json()["id"]
        httpx.post(
            f"{url}/documents/{doc}/items", content=ndjson(boxes, kinds),
            headers={**backend, "content-type": "application/x-ndjson"},
        ).raise_for_status()  # fmt: skip
        minted = []

        def fresh() -> str:
            minted.append(mint(secret, {doc: "read"}, 63))  # due for renewal 3 s after it is made
            return minted[-1]

        with chromium_page() as page:
            page.expose_function("mint", fresh)
            page.goto(f"{url}/health?doc={doc}")
            page.set_content(
                _with(
                    TINY,
                    "new VantageClient({ doc })",
                    "new VantageClient({ doc, token: () => window.mint() })",
                )
            )
            page.wait_for_function("() => window.vantage && window.vantage.state().live", timeout=30_000)
            for dy in range(8):  # ~8 s: two renewals or more
                page.evaluate(f"() => window.vantage.pan(0, {40 * (dy + 1)})")
                page.wait_for_timeout(1000)
            state = page.evaluate("() => window.vantage.state()")
            assert state["live"] and state["transport"] == "ws" and len(state["held"]) > 50
            assert len(minted) >= 3
        with chromium_page() as page:
            page.goto(f"{url}/?doc={doc}#token={mint(secret, {doc: 'read'}, 600)}")
            page.wait_for_function(
                "() => document.getElementById('status').textContent.includes('live')", timeout=30_000
            )
    finally:
        server.terminate()
        server.communicate(timeout=15)
