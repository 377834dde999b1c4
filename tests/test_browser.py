"""The canvas page in a real browser (Debian's Chromium) against a real server process: what the
page holds after real pans and zooms equals brute force over the document, edits show up
live, items far from the origin are drawn where they are, and zoomed out, the tiles it draws ink
where the items are and nowhere else, a pan fetches no tile it holds, a jump fetches only the
tiles near the screen however many its answers name, and a document opening zoomed out is asked
tiled from the first request; a PDF's line at mid zoom is all text, each word across its box."""

import base64
import json
import re
import zlib
from urllib.parse import parse_qs, urlsplit

import httpx
import numpy as np
import oracle
import orjson
import pdfs
import pytest
from browser import artifact, chromium_page
from PIL import Image
from service import NDJSON, ndjson, serving

from app.access import FORGED, mint
from app.importers import Source, batches, detect
from app.launch import launch
from app.simulate.policy import POLICY
from app.tiles import ladder_level, ladder_scale, tiles_over
from spatial import scenes

TEXT = (0x5B, 0x62, 0x70)  # the page's colour for kind "text"
NOTE = (0xFF, 0xD8, 0x66)  # and for "note"
BACKGROUND = (0xE9, 0xEB, 0xEE)
FAR = 1e12  # where the far document's items are


def _import(url: str, name: str, body: bytes) -> str:
    doc = httpx.post(f"{url}/documents", json={"name": name}).json()["id"]
    answer = httpx.post(f"{url}/documents/{doc}/items", content=body, timeout=60, headers=NDJSON)
    assert answer.status_code == 200, answer.text
    return doc


def _far_grid() -> bytes:
    """20 x 20 notes of 10 units with 5-unit gaps, 1e12 units from the origin."""
    lines = [
        orjson.dumps(
            {
                "id": f"n{r}-{c}",
                "x0": FAR + 15 * c,
                "y0": FAR + 15 * r,
                "x1": FAR + 15 * c + 10,
                "y1": FAR + 15 * r + 10,
                "kind": "note",
                "z": 1,
            }
        )
        for r in range(20)
        for c in range(20)
    ]
    return b"\n".join(lines) + b"\n"


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A served store with a 40-page document and the far grid: ``(url, docs, boxes)``."""
    boxes, kinds = scenes.long_document(pages=40, seed=3)
    with serving(tmp_path_factory.mktemp("browser-data")) as url:
        docs = {
            "report": _import(url, "report", ndjson(boxes, kinds)),
            "far": _import(url, "far", _far_grid()),
        }
        yield url, docs, boxes


def _synced(page) -> dict:
    """The page's state once its answer is in, read in the same evaluation that found it synced:
    a frame in between could ask again, leaving the items held behind what was requested."""
    ready = "() => { const s = window.vantage && window.vantage.state(); return !!s && s.synced && s; }"
    return page.wait_for_function(ready, timeout=15_000).json_value()


def _check_held(page, url: str, doc: str, boxes: np.ndarray) -> dict:
    """The page holds exactly what brute force shows in the rect it asked for, at its level of
    detail (the band's items, and aggregates holding the smaller ones), and the server's own
    answer agrees; the screen lies inside that rect. A page drawing tiles (its state has
    ``tiles``) holds the items only, and every tile the tiled answer names near the screen (those
    touching the screen and its overscan margin), whose aggregates include every one the answer
    shows there."""
    state = _synced(page)
    rect, scale, min_px = state["requested"]["rect"], state["requested"]["scale"], state["requested"]["minPx"]
    params = {
        **dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)),
        "scale": scale,
        "min_px": min_px,
        "limit": 100_000,
    }
    served = httpx.get(f"{url}/documents/{doc}/viewport", params=params).json()
    size = 2.0 ** served["band"]
    assert served["band"] == state["band"] and size >= min_px / scale
    ids = [f"i{i}" for i in range(len(boxes))]
    oracle.check_shown(boxes, ids, rect, size, served["items"])
    held = set(state["held"])
    if state.get("tiles"):
        tiled = httpx.get(f"{url}/documents/{doc}/viewport", params={**params, "tiles": "true"}).json()
        assert {k: v for k, v in state["tiles"].items() if k != "version"} == tiled["tiles"]
        assert (
            held
            == {item["id"] for item in tiled["items"]}
            == {i["id"] for i in served["items"] if "agg" not in i}
        )
        near = _tiles_near(state)
        assert set(state["tilesHeld"]) == {_tile_path(doc, state["tiles"], t) for t in near}
        margin = _grown(state["told"], POLICY["overscan"])
        shown = {i["id"] for i in served["items"] if "agg" in i and _touch(i, margin)}
        assert shown <= set(state["aggregates"])
    else:
        assert held == {item["id"] for item in served["items"]}
    assert not state["truncated"]
    x0, y0, x1, y1 = state["viewport"]
    assert rect[0] <= x0 and rect[1] <= y0 and x1 <= rect[2] and y1 <= rect[3]
    return state


def _grown(rect: list, share: float) -> list:
    """``rect`` grown by ``share`` of its size on each side, as the client grows the screen."""
    dx, dy = (rect[2] - rect[0]) * share, (rect[3] - rect[1]) * share
    return [rect[0] - dx, rect[1] - dy, rect[2] + dx, rect[3] + dy]


def _touch(item: dict, rect: list) -> bool:
    return item["x0"] <= rect[2] and item["x1"] >= rect[0] and item["y0"] <= rect[3] and item["y1"] >= rect[1]


def _tiles_touching(sheet: dict, rect: list) -> set[tuple[int, int]]:
    """The tiles of ``sheet``'s band and level that ``rect`` touches, as the server numbers them."""
    tx0, ty0, tx1, ty1 = tiles_over(sheet["band"], sheet["z"], tuple(rect))
    return {(tx, ty) for tx in range(tx0, tx1 + 1) for ty in range(ty0, ty1 + 1)}


def _tiles_near(state: dict) -> set[tuple[int, int]]:
    """The tiles the page should hold: of those its answer names, the ones touching the screen
    its client was last told of and the overscan margin around it; checked against the range
    the page says it aims at."""
    sheet, screen = state["tiles"], state["told"]
    near = _tiles_touching(sheet, _grown(screen, POLICY["overscan"]))
    tx0, ty0, tx1, ty1 = sheet["range"]
    near = {(tx, ty) for tx, ty in near if tx0 <= tx <= tx1 and ty0 <= ty <= ty1}
    nx0, ny0, nx1, ny1 = state["tilesNear"] or (0, 0, -1, -1)
    assert near == {(tx, ty) for tx in range(nx0, nx1 + 1) for ty in range(ny0, ny1 + 1)}
    return near


def _tile_path(doc: str, sheet: dict, tile: tuple[int, int]) -> str:
    """The path (and query) the page fetches ``sheet``'s tile at ``tile`` (tx, ty) by."""
    band, z, version = sheet["band"], sheet["z"], sheet["version"]
    return f"/documents/{doc}/tiles/{band}/{z}/{tile[0]}/{tile[1]}?version={version}"


def _drawn(page, until: str = "(s) => true", timeout: float = 15_000) -> dict:
    """Wait until the canvas shows a frame drawn from the page's current camera and current held
    set (``drawn``), the answer for that view is in (``synced``), no "go to" is still on its way
    to move the camera, and the JS predicate ``until(state)`` holds; return that very state.

    The state is read in the same evaluation that checked it, so nothing can move in between.
    """
    ready = f"""() => {{
        const s = window.vantage && window.vantage.state();
        return !!s && s.synced && s.drawn && s.goto.pending === 0 && !!({until})(s) && s;
    }}"""
    return page.wait_for_function(ready, timeout=timeout).json_value()


def _shot(page, name: str, until: str = "(s) => true") -> tuple[dict, np.ndarray]:
    """``_drawn``'s state and a screenshot of the frame drawn from it (RGB), saved as ``name``.

    If the page drew a different frame while the screenshot was taken (its camera or held set
    moved on), the pair would not match: wait and take both again.
    """
    path = artifact(name)
    for _ in range(5):
        state = _drawn(page, until)
        page.screenshot(path=path)
        after = page.evaluate("() => window.vantage.state()")
        if after["drawn"] and after["painted"] == state["painted"]:  # the same picture throughout
            return state, np.asarray(Image.open(path).convert("RGB"))
    raise AssertionError(f"the page kept drawing new frames while {name} was taken")


def _at(view: list) -> str:
    """A JS predicate: the screen shows exactly ``view`` (a state's ``viewport``)."""
    return f"(s) => s.viewport.every((v, i) => v === {json.dumps(view)}[i])"


def _pixels(page, name: str, colour: tuple, until: str = "(s) => true") -> int:
    """How many pixels of a screenshot are ``colour``, once a frame matching ``until`` is drawn."""
    _, shot = _shot(page, name, until)
    return int((shot.reshape(-1, 3) == colour).all(axis=1).sum())


def test_the_page_holds_what_brute_force_shows_as_a_person_pans_and_zooms(site):
    url, docs, boxes = site
    with chromium_page() as page:
        page.goto(f"{url}/?doc={docs['report']}")
        first = _check_held(page, url, docs["report"], boxes)
        assert len(first["held"]) > 100 and first["transport"] == "ws"
        start = _pixels(page, "browser-start.png", TEXT, _at(first["viewport"]))
        assert start > 500  # word boxes drawn, not a blank canvas

        page.mouse.move(640, 400)  # drag up and left
        page.mouse.down()
        page.mouse.move(520, 100, steps=12)
        page.mouse.up()
        _check_held(page, url, docs["report"], boxes)

        for _ in range(6):  # scroll down a few screens with the wheel
            page.mouse.wheel(0, 900)
            page.wait_for_timeout(30)
        scrolled = _check_held(page, url, docs["report"], boxes)
        assert scrolled["viewport"][1] > first["viewport"][1] + 2000

        page.keyboard.down("Control")  # zoom out around the cursor: level of detail kicks in
        page.mouse.wheel(0, 250)
        page.keyboard.up("Control")
        zoomed = _check_held(page, url, docs["report"], boxes)
        assert zoomed["scale"] < scrolled["scale"] / 5
        for _ in range(3):  # further out: aggregates stand in for the text, then for whole pages
            page.keyboard.press("-")
            farther = _check_held(page, url, docs["report"], boxes)
        # held inline, or zoomed out far enough, in the tiles the page draws
        assert any(i.startswith("~") for i in farther["held"]) or farther["aggregates"]

        page.locator("canvas").focus()
        for key in ("PageDown", "ArrowRight", "=", "="):
            page.keyboard.press(key)
        panned = _check_held(page, url, docs["report"], boxes)
        _shot(page, "browser-panned.png", _at(panned["viewport"]))


def test_an_edit_over_http_shows_up_without_reloading(site):
    url, docs, _ = site
    with chromium_page() as page:
        page.goto(f"{url}/?doc={docs['report']}")
        view = _synced(page)["viewport"]
        x0, y0 = view[:2]
        box = {"x0": x0 + 40, "y0": y0 + 40, "x1": x0 + 240, "y1": y0 + 140, "kind": "note", "z": 9}
        assert httpx.put(f"{url}/documents/{docs['report']}/items/sticky", json=box).status_code == 201
        page.wait_for_function("() => window.vantage.state().held.includes('sticky')", timeout=10_000)
        held = {item["id"]: item for item in page.evaluate("() => window.vantage.items()")}
        assert {k: held["sticky"][k] for k in box} == box
        sticky = f"(s) => s.held.includes('sticky') && ({_at(view)})(s)"
        drawn = _pixels(page, "browser-edit.png", NOTE, sticky)
        assert drawn > 10_000  # 200 x 100 units drawn at scale >= 0.5
        assert httpx.delete(f"{url}/documents/{docs['report']}/items/sticky").status_code == 200
        page.wait_for_function("() => !window.vantage.state().held.includes('sticky')", timeout=10_000)


def test_the_http_fallback_keeps_the_same_set(site):
    url, docs, boxes = site
    with chromium_page() as page:
        page.goto(f"{url}/?doc={docs['report']}")
        _synced(page)
        page.evaluate("() => window.vantage.useHttp()")
        page.mouse.move(640, 400)
        for _ in range(4):
            page.mouse.wheel(0, 1200)
            page.wait_for_timeout(30)
        state = _check_held(page, url, docs["report"], boxes)
        assert state["transport"] == "http"
        page.locator("canvas").focus()
        for key in ("-", "-", "-", "-", "PageDown", "=", "="):  # diffs across bands, over HTTP
            page.keyboard.press(key)
            state = _check_held(page, url, docs["report"], boxes)
        assert state["transport"] == "http" and state["band"] is not None


def test_items_far_from_the_origin_are_drawn_where_they_are(site):
    url, docs, _ = site
    with chromium_page() as page:
        page.goto(f"{url}/?doc={docs['far']}")
        before = _drawn(page)["goto"]["done"]
        page.fill("#goto", "n10-10")  # "go to" an item id: centred, zoomed to read it
        page.press("#goto", "Enter")
        # The page fetches the item, then moves: wait for that move, and a frame drawn after it.
        cx = cy = FAR + 15 * 10 + 5  # n10-10's centre
        centred = (
            f"(s) => s.goto.done > {before} && Math.abs((s.viewport[0] + s.viewport[2]) / 2 - {cx!r}) < 0.01"
            f" && Math.abs((s.viewport[1] + s.viewport[3]) / 2 - {cy!r}) < 0.01"
        )
        state, shot = _shot(page, "browser-far.png", centred)
        assert state["goto"]["last"] == {"seq": before + 1, "text": "n10-10", "outcome": "moved"}
        assert state["viewport"][0] > FAR - 1e4 and len(state["held"]) > 50
        top = page.evaluate("() => document.getElementById('canvas').getBoundingClientRect().top")
        x, y, scale = state["viewport"][0], state["viewport"][1], state["scale"]
        assert scale > 2  # a 5-unit gap is > 10 px: float32 coordinates would smear it away
        for r, c in ((10, 10), (9, 11), (11, 9)):
            ix0, iy0 = FAR + 15 * c, FAR + 15 * r  # each note's centre is its colour, each gap is not
            px = lambda u: int((u - x) * scale)  # float64 subtraction first, as the page does
            py = lambda v: int((v - y) * scale + top)
            assert tuple(shot[py(iy0 + 5), px(ix0 + 5)]) == NOTE
            assert tuple(shot[py(iy0 + 5), px(ix0 + 12.5)]) == BACKGROUND


def test_the_canvas_keeps_its_size_whatever_the_status_line_says(site):
    # An empty status line once had no height: the canvas shrank when the first status
    # appeared, after the first request had been sized for the taller screen.
    url, docs, _ = site
    with chromium_page() as page:
        page.goto(f"{url}/?doc={docs['report']}")
        heights = page.evaluate(
            """() => ['', 'x', 'a long status '.repeat(80)].map((text) => {
                 document.getElementById('status').textContent = text;
                 return document.getElementById('canvas').getBoundingClientRect().height;
               })"""
        )
    assert len(set(heights)) == 1 and heights[0] > 600, heights


BACKGROUND_RGB = np.array(BACKGROUND)


def _document_share_drawn(state: dict, shot: np.ndarray, bounds: list[float], top: float) -> float:
    """The share of the document's on-screen area (its bounds, clipped to the canvas) whose
    pixels are not the background."""
    x, y, scale = state["viewport"][0], state["viewport"][1], state["scale"]
    h, w = min(shot.shape[0] - int(top), int(state["painted"]["height"])), shot.shape[1]  # the canvas only
    c0, c1 = int(max(0, np.floor((bounds[0] - x) * scale))), int(min(w, np.ceil((bounds[2] - x) * scale)))
    r0, r1 = int(max(0, np.floor((bounds[1] - y) * scale))), int(min(h, np.ceil((bounds[3] - y) * scale)))
    area = shot[int(top) + r0 : int(top) + r1, c0 : max(c1, c0 + 1)]
    assert area.size, "the document is not on screen"
    return float((area != BACKGROUND_RGB).any(axis=2).mean())


def _settled(page) -> str:
    """A predicate: the answer for the screen has arrived, whole (no blank edge)."""
    return "(s) => s.covered"


@pytest.mark.slow(seconds=15)  # the demo documents made (1.3M items), once a session
def test_fit_on_the_demo_report_draws_the_whole_document(demo):
    url, docs = demo
    doc = docs["Demo: 2000-page report"]
    bounds = httpx.get(f"{url}/documents/{doc}").json()["bounds"]
    with chromium_page() as page:
        page.goto(f"{url}/?doc={doc}")
        _synced(page)
        page.click("#fit")
        state, shot = _shot(page, "browser-fit.png", "(s) => s.covered && s.scale < 0.001")
        top = page.evaluate("() => document.getElementById('canvas').getBoundingClientRect().top")
        assert state["band"] is not None and len(state["held"]) + len(state["aggregates"]) > 0
        assert _document_share_drawn(state, shot, bounds, top) >= 0.9


def test_zooming_out_to_fit_and_back_never_shows_the_document_blank(demo):
    url, docs = demo
    doc = docs["Demo: 2000-page report"]
    bounds = httpx.get(f"{url}/documents/{doc}").json()["bounds"]
    with chromium_page() as page:
        page.goto(f"{url}/?doc={doc}")
        start = _synced(page)["scale"]  # page width
        top = page.evaluate("() => document.getElementById('canvas').getBoundingClientRect().top")
        steps = int(np.ceil(np.log(start / 5e-4) / np.log(4)))
        zooms = [0.25] * steps + [4.0] * steps  # out past the whole document, and back in
        bands = []
        for i, factor in enumerate(zooms):
            page.evaluate(f"() => window.vantage.zoomAt(640, 50, {factor})")
            state, shot = _shot(page, f"browser-zoom-{i:02d}.png", _settled(page))
            share = _document_share_drawn(state, shot, bounds, top)
            assert share >= 0.9, f"at scale {state['scale']:.3g} only {share:.0%} of the document is drawn"
            bands.append(state["band"])
        assert len(set(bands)) >= 4  # the zoom went through several bands, out and back


INK = (0x1F, 0x24, 0x30)  # the page's colour for an item's text


def test_zoomed_in_far_enough_the_page_draws_the_words_text(site):
    url, _, _ = site
    words = ["Quarterly", "revenue", "rose", "MMMM", "WWWW", "sharply"]
    items = [{"id": "p", "x0": 0, "y0": 0, "x1": 612, "y1": 792, "kind": "page", "z": 0}]
    boxes = []
    for row in range(12):
        for col, word in enumerate(words):
            box = (72 + 76 * col, 100 + 20 * row, 72 + 76 * col + 70, 100 + 20 * row + 12)
            boxes.append(box)
            items.append(
                {"id": f"w{row}-{col}", **dict(zip(("x0", "y0", "x1", "y1"), box, strict=True))}
                | {"kind": "text", "z": 1, "data": {"text": word}}
            )
    doc = _import(url, "words", b"".join(orjson.dumps(i) + b"\n" for i in items))
    target = boxes[3]  # "MMMM" in the first row: wide dark glyphs

    def ink(state: dict, shot: np.ndarray, top: float) -> tuple[int, int]:
        """Pixels of the text colour inside the target's box, and outside every word's box."""
        x, y, scale = state["viewport"][0], state["viewport"][1], state["scale"]
        canvas = shot[int(top) :]
        mask = (canvas == INK).all(axis=2)
        inside = np.zeros_like(mask)
        for x0, y0, x1, y1 in boxes:
            c0, c1 = max(0, int(np.floor((x0 - x) * scale))), int(np.ceil((x1 - x) * scale)) + 1
            r0, r1 = max(0, int(np.floor((y0 - y) * scale))), int(np.ceil((y1 - y) * scale)) + 1
            inside[r0:r1, c0:c1] = True
            if (x0, y0, x1, y1) == target:
                in_target = int(mask[r0:r1, c0:c1].sum())
        return in_target, int((mask & ~inside).sum())

    with chromium_page() as page:
        page.goto(f"{url}/?doc={doc}")
        _synced(page)
        top = page.evaluate("() => document.getElementById('canvas').getBoundingClientRect().top")
        cx, cy = (target[0] + target[2]) / 2, (target[1] + target[3]) / 2
        page.evaluate(f"() => window.vantage.centreOn({cx}, {cy}, 0.5)")  # words 6 px tall: bars
        far, shot = _shot(page, "browser-text-out.png", "(s) => s.scale === 0.5 && s.covered")
        assert ink(far, shot, top) == (0, 0)
        assert (shot[int(top) :] == TEXT).all(axis=2).sum() > 1000  # the words' grey bars
        page.evaluate(f"() => window.vantage.centreOn({cx}, {cy}, 6)")  # 72 px tall: their text
        near, shot = _shot(page, "browser-text-in.png", "(s) => s.scale === 6 && s.covered")
        inside, outside = ink(near, shot, top)
        assert inside > 500, "no text drawn in the word's box"
        assert outside == 0, "text drawn outside its word's box (not clipped)"


def test_a_pdf_line_at_mid_zoom_is_drawn_as_text_every_word_of_it_across_its_box(site, tmp_path):
    """Words with and without ascenders ("ace", "The"), imported from a PDF, are as tall as one
    another, so at a zoom where the line is just legible every word is text (none a grey bar),
    each drawn across its box, where the PDF draws it."""
    url, _, _ = site
    path = tmp_path / "line.pdf"
    path.write_bytes(pdfs.document([pdfs.page(pdfs.line(72, 700, "The ace was on a quiet ship"))]))
    body = b"".join(
        b + b"\n" for batch in batches(Source.of(path), detect(path), 1 << 16, 4096) for b in batch.bodies
    )
    words = [i for i in map(orjson.loads, body.splitlines()) if i["kind"] == "text"]
    assert [w["data"]["text"] for w in words] == ["The", "ace", "was", "on", "a", "quiet", "ship"]
    # and a word spaced out in the PDF, read whole: its box far wider than its letters set tight
    spaced = {"id": "spaced", "x0": 72, "y0": 100, "x1": 232, "y1": 114, "kind": "text", "z": 3}
    words.append(spaced | {"data": {"text": "wide"}})
    doc = _import(url, "pdf-line", body + orjson.dumps(words[-1]) + b"\n")
    with chromium_page() as page:
        page.goto(f"{url}/?doc={doc}")
        _synced(page)
        top = page.evaluate("() => document.getElementById('canvas').getBoundingClientRect().top")
        # the line about 10 px tall on screen, "ace"'s ink (its x-height) about 4 px
        page.evaluate("() => window.vantage.centreOn(150, 95, 0.75)")
        state, shot = _shot(page, "browser-pdf-line.png", "(s) => s.scale === 0.75 && s.covered")
        x, y, scale = state["viewport"][0], state["viewport"][1], state["scale"]
        canvas = shot[int(top) :].astype(int)
        for word in words:
            c0, c1 = int(np.ceil((word["x0"] - x) * scale)), int(np.floor((word["x1"] - x) * scale))
            r0, r1 = int(np.ceil((word["y0"] - y) * scale)), int(np.floor((word["y1"] - y) * scale))
            box = canvas[r0:r1, c0:c1]
            said = word["data"]["text"]
            assert not (box == TEXT).all(axis=2).any(), f"{said!r} is drawn as a bar"
            dark = (np.abs(box - INK).max(axis=2) < 90).any(axis=0)  # the columns its glyphs ink
            assert dark.any(), f"{said!r} is not drawn"
            inked = np.flatnonzero(dark)
            # across its box: ink near both ends (but for its glyphs' side bearings, stretched too)
            span = box.shape[1]
            assert inked[0] <= 2 + span / 20 and inked[-1] >= span * 0.95 - 3, (
                f"{said!r} inks {inked[[0, -1]]} of {span}"
            )


def test_a_phrase_that_wraps_is_highlighted_on_each_line_not_as_one_block(site):
    url, _, _ = site
    lines = [["sits", "interfaces", "on"], ["top", "of", "it"]]  # "interfaces on top" wraps
    items = [{"id": "p", "x0": 0, "y0": 0, "x1": 612, "y1": 792, "kind": "page", "z": 0}]
    for row, words in enumerate(lines):
        for col, word in enumerate(words):
            box = {"x0": 72 + 100 * col, "y0": 100 + 20 * row, "x1": 142 + 100 * col, "y1": 112 + 20 * row}
            items.append({"id": f"w{row}-{col}", **box, "kind": "text", "z": 1, "data": {"text": word}})
    doc = _import(url, "wrap", b"".join(orjson.dumps(i) + b"\n" for i in items))
    with chromium_page() as page:
        page.goto(f"{url}/?doc={doc}")
        _synced(page)
        page.fill("#find", "interfaces on top")
        state = page.wait_for_function(
            "() => { const s = window.vantage.state(); return s.find.hits === 1 && s.highlight && s; }",
            timeout=10_000,
        ).json_value()
        # a box a line: the first line's two words, the second line's one
        assert state["highlight"]["boxes"] == [[172, 100, 342, 112], [72, 120, 142, 132]]
        _, shot = _shot(page, "browser-find-wrap.png", "(s) => s.find.at === 0")
        top = page.evaluate("() => document.getElementById('canvas').getBoundingClientRect().top")
        x, y, scale = state["viewport"][0], state["viewport"][1], state["scale"]

        def pixel(cx: float, cy: float) -> np.ndarray:
            return shot[int((cy - y) * scale + top), int((cx - x) * scale)].astype(int)

        white = np.array([255, 255, 255])
        assert np.abs(pixel(230, 106) - white).max() > 30  # the hit on the first line is marked
        assert np.abs(pixel(100, 126) - white).max() > 30  # and on the second
        assert np.abs(pixel(157, 126) - white).max() < 10  # not between the second line's words after it
        assert np.abs(pixel(150, 106) - white).max() < 10  # nor between the first line's before it


def test_the_find_box_highlights_a_phrase_across_words_and_enter_steps_through_hits(site):
    url, _, _ = site
    words = ["these", "first", "rows", "and", "these", "first"]  # "these first" twice, each across two words
    items = [{"id": "p", "x0": 0, "y0": 0, "x1": 612, "y1": 792, "kind": "page", "z": 0}]
    for row in range(2):
        for col, word in enumerate(words[row * 3 : row * 3 + 3]):
            box = {
                "x0": 72 + 80 * col,
                "y0": 100 + 300 * row,
                "x1": 72 + 80 * col + 70,
                "y1": 112 + 300 * row,
            }
            items.append({"id": f"w{row}-{col}", **box, "kind": "text", "z": 1, "data": {"text": word}})
    doc = _import(url, "find", b"".join(orjson.dumps(i) + b"\n" for i in items))
    found = (255, 200, 0)  # the hit's fill over the page's white, nearly

    with chromium_page() as page:
        page.goto(f"{url}/?doc={doc}")
        _synced(page)
        page.fill("#find", "THESE First")  # typed: searched once typing pauses
        state = page.wait_for_function(
            "() => { const s = window.vantage.state(); return s.find.hits === 2 && s.find.at === 0 && s; }",
            timeout=10_000,
        ).json_value()
        assert state["find"]["count"] == "1 of 2" and state["highlight"]["box"] == [72, 100, 222, 112]
        _, shot = _shot(page, "browser-find-first.png", "(s) => s.find.at === 0")
        top = page.evaluate("() => document.getElementById('canvas').getBoundingClientRect().top")
        x, y, scale = state["viewport"][0], state["viewport"][1], state["scale"]
        r, c = int((106 - y) * scale + top), int((150 - x) * scale)  # inside the hit, between its words
        assert np.abs(shot[r, c].astype(int) - np.array(found) * 0.45 - 255 * 0.55).max() < 40, shot[r, c]
        page.press("#find", "Enter")
        state = _drawn(page, "(s) => s.find.at === 1")
        assert state["find"]["count"] == "2 of 2" and state["highlight"]["box"] == [152, 400, 302, 412]
        x0, y0, x1, y1 = state["viewport"]
        assert x0 < 227 < x1 and y0 < 406 < y1  # the second hit is on screen
        page.press("#find", "Shift+Enter")
        assert _drawn(page, "(s) => s.find.at === 0")["find"]["count"] == "1 of 2"
        pages = page.evaluate(
            """async () => {
                const first = await window.vantage.client.search("these FIRST", { limit: 1 });
                const second = await first.next();
                return [first.hits.map((h) => h.ids), second.hits.map((h) => h.ids), !!second.next];
            }"""
        )  # vantage-client.js's search(), a page at a time
        assert pages == [[["w0-0", "w0-1"]], [["w1-1", "w1-2"]], False]


def _speckled(seed: int = 5) -> tuple[np.ndarray, bytes]:
    """Notes of 2 units: 20,000 strewn over a 4,000-unit square, 20,000 packed in a disc of
    radius 300 at its middle. Zoomed out to fit, too many to send, so coarse aggregates hold
    them, their boxes mostly empty around the disc."""
    rng = np.random.default_rng(seed)
    strewn = rng.uniform(0, 4000, (20_000, 2))
    radius, angle = 300 * np.sqrt(rng.uniform(0, 1, 20_000)), rng.uniform(0, 2 * np.pi, 20_000)
    disc = np.column_stack([2000 + radius * np.cos(angle), 2000 + radius * np.sin(angle)])
    xy = np.concatenate([strewn, disc])
    boxes = np.column_stack([xy, xy + 2])
    lines = [
        orjson.dumps({"id": f"r{i}", "x0": b[0], "y0": b[1], "x1": b[2], "y1": b[3], "kind": "note"})
        for i, b in enumerate(boxes.tolist())
    ]
    return boxes, b"\n".join(lines) + b"\n"


@pytest.fixture(scope="module")
def speckled(site):
    """The speckled notes (``_speckled``) in the site's store: ``(url, doc, boxes)``."""
    url, _, _ = site
    boxes, body = _speckled()
    return url, _import(url, "speckled", body), boxes


@pytest.fixture(scope="module")
def strewn(site):
    """5,000 notes of 2 units strewn over a 16,000-unit square, in the site's store: zoomed out,
    far fewer than an answer's budget, so the band is the zoom's wherever the screen is."""
    url, _, _ = site
    xy = np.random.default_rng(11).uniform(0, 16_000, (5_000, 2))
    lines = [
        orjson.dumps({"id": f"s{i}", "x0": x, "y0": y, "x1": x + 2, "y1": y + 2, "kind": "note"})
        for i, (x, y) in enumerate(xy.tolist())
    ]
    return url, _import(url, "strewn", b"\n".join(lines) + b"\n")


def _all_tiles_held(also: str = "true") -> str:
    """A JS predicate: the page draws tiles, holds every one its answer names near the screen,
    and ``also``."""
    return (
        "(s) => !!s.tiles && !!s.tilesNear && s.tilesHeld.length === "
        "(s.tilesNear[2] - s.tilesNear[0] + 1) * (s.tilesNear[3] - s.tilesNear[1] + 1) && "
        f"({also})"
    )


def _tile_requests(asked: list[str]) -> list[str]:
    return [u for u in asked if "/tiles/" in u]


def _tile_bits(url: str, path: str) -> tuple[dict, dict[str, np.ndarray]]:
    """The tile at ``path`` as the server sends it, and each kind's layer as (size, size) bools:
    base64, then zlib, then bits least significant first, row by row."""
    body = httpx.get(url + path).json()
    n = body["size"]
    layers = {
        kind: np.unpackbits(
            np.frombuffer(zlib.decompress(base64.b64decode(text)), np.uint8), bitorder="little"
        )
        .reshape(n, n)
        .astype(bool)
        for kind, text in body["layers"].items()
    }
    return body, layers


def _touched(
    boxes: np.ndarray, view: tuple[float, float, float], shape: tuple[int, int], grow: float
) -> np.ndarray:
    """The screen pixels (``shape``: rows, columns) that canvas ``boxes`` (n, 4) overlap, each box
    grown by ``grow`` pixels on every side (shrunk, when negative), seen from ``view`` (x, y at
    the screen's top-left, scale)."""
    x, y, scale = view
    h, w = shape
    c0 = np.clip(np.floor((boxes[:, 0] - x) * scale - grow), 0, w).astype(np.int64)
    r0 = np.clip(np.floor((boxes[:, 1] - y) * scale - grow), 0, h).astype(np.int64)
    c1 = np.clip(np.ceil((boxes[:, 2] - x) * scale + grow), 0, w).astype(np.int64)
    r1 = np.clip(np.ceil((boxes[:, 3] - y) * scale + grow), 0, h).astype(np.int64)
    out = np.zeros(shape, bool)
    for a, b, c, d in zip(*(v[(c1 > c0) & (r1 > r0)].tolist() for v in (r0, r1, c0, c1)), strict=True):
        out[a:b, c:d] = True
    return out


def test_zoomed_out_the_page_draws_tiles_inking_where_the_notes_are_and_nowhere_else(speckled):
    """Zoomed out, the page fetches the tiles its answer names and draws their bits: every pixel
    a note overlaps is the notes' colour, every pixel farther than a pixel from every note is the
    canvas's, and the picture is the served tiles' set bits, each inking the pixels it touches:
    at the tiles' own scale, where the page draws them, a bit a pixel."""
    url, doc, boxes = speckled
    with chromium_page() as page:
        asked = []
        page.on("request", lambda request: asked.append(request.url))
        page.goto(f"{url}/?doc={doc}")
        _drawn(page)
        page.evaluate("() => window.vantage.centreOn(2000, 2000, 0.15)")
        state, shot = _shot(page, "browser-tiles.png", _all_tiles_held("s.scale < 0.16"))
        top = page.evaluate("() => document.getElementById('canvas').getBoundingClientRect().top")
    assert top == int(top)
    sheet, held = state["tiles"], state["tilesHeld"]
    requested = {u.removeprefix(url) for u in _tile_requests(asked)}
    assert held and set(held) <= requested  # the page fetched the tiles it draws
    assert state["transport"] == "http" and not any(i.startswith("~") for i in state["held"])
    x, y, scale = state["viewport"][0], state["viewport"][1], state["scale"]
    assert scale == ladder_scale(sheet["z"])  # drawn at the tiles' own scale, on whole pixels:
    assert abs(x * scale - round(x * scale)) < 1e-6 and abs(y * scale - round(y * scale)) < 1e-6
    view, shape = (x, y, scale), (int(state["painted"]["height"]), int(state["painted"]["width"]))
    canvas = shot[int(top) : int(top) + shape[0], : shape[1]]
    drawn = (canvas == NOTE).all(axis=2)
    assert (drawn | (canvas == BACKGROUND).all(axis=2)).all()  # no box, no blend: bits, in the notes' colour

    # Brute force over the notes: each pixel a note overlaps is inked; one farther than a pixel
    # from every note is not (a mask's members may be finer aggregates, within a pixel of theirs).
    must, may = _touched(boxes, view, shape, -1e-6), _touched(boxes, view, shape, 1.0)
    missed, stray = must & ~drawn, drawn & ~may
    assert not missed.any(), (
        f"{missed.sum()} pixels of notes not inked, e.g. {np.argwhere(missed)[:5].tolist()}"
    )
    assert not stray.any(), (
        f"{stray.sum()} pixels inked away from every note, e.g. {np.argwhere(stray)[:5].tolist()}"
    )
    assert must.sum() > 5_000 and (~may).sum() > 100_000  # specks and gaps both on screen
    assert drawn[int((2000 - y) * scale), int((2000 - x) * scale)]  # the packed disc

    # Brute force over the tiles the page holds: each set bit inks every pixel it touches (to
    # within float noise at pixel edges) and no other; here, exactly its own pixel.
    bits = []
    for path in held:
        body, layers = _tile_bits(url, path)
        assert not body["aggregates"]["boxed"] and set(layers) <= {"note"}
        n, s = body["size"], body["scale"]
        for r, c in np.argwhere(layers.get("note", np.zeros((n, n), bool))).tolist():
            px, py = body["tx"] * n + c, body["ty"] * n + r
            bits.append((px / s, py / s, (px + 1) / s, (py + 1) / s))
    bits = np.array(bits)
    inner, outer = _touched(bits, view, shape, -1e-6), _touched(bits, view, shape, 1e-6)
    assert (inner <= drawn).all() and (drawn <= outer).all()
    assert (drawn == inner).all()


def test_panning_zoomed_out_fetches_no_tile_the_page_holds(strewn):
    """A pan by part of a screen asks for the tiles it does not hold only, and so does a jump back:
    no tile is fetched twice, and the tiles the views share are drawn from those held."""
    url, doc = strewn
    with chromium_page() as page:
        asked = []
        page.on("request", lambda request: asked.append(request.url))
        page.goto(f"{url}/?doc={doc}")
        _drawn(page)
        page.evaluate("() => window.vantage.centreOn(8000, 8000, 0.15)")
        before = _drawn(page, _all_tiles_held("s.scale < 0.16"))
        first = _tile_requests(asked)
        page.mouse.move(900, 500)  # drag the content 700 px left and 200 px up
        page.mouse.down()
        page.mouse.move(200, 300, steps=10)
        page.mouse.up()
        moved = f"s.tiles.range.join() !== {json.dumps(','.join(map(str, before['tiles']['range'])))}"
        after = _drawn(page, _all_tiles_held(moved))
        panned = _tile_requests(asked)[len(first) :]
        page.evaluate("() => window.vantage.centreOn(8000, 8000, 0.15)")
        back = _drawn(page, _all_tiles_held(f"({_at(before['viewport'])})(s)"))
        state = page.evaluate("() => window.vantage.state()")
    every = _tile_requests(asked)
    assert after["scale"] == before["scale"] and after["tiles"]["band"] == before["tiles"]["band"]
    assert after["viewport"][0] > before["viewport"][0] + 600 / after["scale"]
    assert first and panned  # the pan's answer named tiles not held: fetched
    assert len(every) == len(set(every)), "a tile fetched twice"
    kept = set(before["tilesHeld"]) & set(after["tilesHeld"])
    assert kept and not kept & {u.removeprefix(url) for u in panned}  # held: drawn, not fetched again
    assert set(back["tilesHeld"]) & set(before["tilesHeld"])  # back where it started, from tiles held
    assert state["tileFetches"] == len(every)


APART = 2e6  # units between the twin fields, along x and along y


@pytest.fixture(scope="module")
def twins(site):
    """Two fields of 20,000 notes of 2 units, each strewn over a 16,000-unit square, the second
    APART units right of and below the first, in the site's store: ``(url, doc)``."""
    url, _, _ = site
    xy = np.random.default_rng(13).uniform(0, 16_000, (40_000, 2))
    xy[20_000:] += APART
    lines = [
        orjson.dumps({"id": f"t{i}", "x0": x, "y0": y, "x1": x + 2, "y1": y + 2, "kind": "note"})
        for i, (x, y) in enumerate(xy.tolist())
    ]
    return url, _import(url, "twins", b"\n".join(lines) + b"\n")


def _views(asked: list[str]) -> list[str]:
    """The /viewport and /diff requests in ``asked``."""
    return [u for u in asked if re.search(r"/documents/[^/]+/(viewport|diff)\?", u)]


def _tiles_named(request: str) -> int:
    """How many tiles a tiled /viewport or /diff request is answered with, when the rect it asks
    for holds aggregates: those of that rect at the ladder level of its scale."""
    query = parse_qs(urlsplit(request).query)
    if query.get("tiles") != ["true"]:
        return 0
    if "to" in query:
        rect = tuple(float(v) for v in query["to"][0].split(","))
    else:
        rect = tuple(float(query[k][0]) for k in ("x0", "y0", "x1", "y1"))
    tx0, ty0, tx1, ty1 = tiles_over(0, ladder_level(float(query["scale"][0])), rect)
    return (tx1 - tx0 + 1) * (ty1 - ty0 + 1)


def test_a_jump_fetches_only_the_tiles_near_the_screen_however_many_its_answers_name(twins):
    """Zoomed out, a jump from one field to the other reads as a fast fling: the page asks for a
    rect stretched millions of units ahead, whose tiled answer names millions of tiles. The page
    fetches only those touching the screen and its overscan margin, and draws the notes under
    the screen from them; a pan then fetches the tiles entering the margin, without a new answer."""
    url, doc = twins
    s = ladder_scale(11)  # 0.149 pixels a unit, on the tiles' ladder: the page draws at it as is
    with chromium_page() as page:
        asked, loading = [], {"now": 0, "most": 0}  # tile requests on their way: now, and at most

        def sent(request) -> None:
            asked.append(request.url)
            if "/tiles/" in request.url:
                loading["now"] += 1
                loading["most"] = max(loading["most"], loading["now"])

        def done(request) -> None:
            if "/tiles/" in request.url:
                loading["now"] -= 1

        page.on("request", sent)
        page.on("requestfinished", done)
        page.on("requestfailed", done)
        page.goto(f"{url}/?doc={doc}")
        _drawn(page)
        page.evaluate(f"() => window.vantage.centreOn(8000, 8000, {s})")  # a zoom: no fling
        width = _drawn(page, _all_tiles_held(f"s.scale === {s}"))["painted"]["width"]
        before = len(asked)
        # The jump: the margin's right edge lands 10 px short of a tile's edge (the screen's left
        # on a whole pixel), so a pan of 20 px brings a column of tiles into the margin.
        k = round((APART + 8000) * s / 512)
        left = (512 * k - 10 - (1 + POLICY["overscan"]) * width) / s
        page.evaluate(f"() => window.vantage.centreOn({left + width / 2 / s}, {APART + 8000}, {s})")
        jumped = _drawn(page, _all_tiles_held(f"s.viewport[0] > {APART / 2}"), timeout=30_000)
        notes = _pixels(page, "browser-jump.png", NOTE, _at(jumped["viewport"]))
        after_jump = asked[before:]
        asks = len(asked)
        page.mouse.move(640, 400)
        page.mouse.down()
        page.mouse.move(620, 400)  # the screen 20 px right
        page.mouse.up()
        column = jumped["tilesNear"][2] + 1
        panned = _drawn(page, _all_tiles_held(f"s.tilesNear[2] === {column}"))
        after_pan = _tile_requests(asked[asks:])

    assert max(map(_tiles_named, _views(after_jump))) > 100_000  # read as a fling: a huge range named
    assert loading["most"] <= 6  # a few tiles at a time, nearest the screen first
    fetched = [u.removeprefix(url) for u in _tile_requests(after_jump)]
    assert fetched and len(fetched) == len(set(fetched)), "a tile fetched twice"
    near = {_tile_path(doc, jumped["tiles"], t) for t in _tiles_near(jumped)}
    assert set(jumped["tilesHeld"]) == near and len(near) <= 35  # a screen and its margin: 7 x 5 at most
    assert set(fetched) <= near, f"{len(set(fetched) - near)} tiles away from the screen fetched"
    assert jumped["scale"] == s and jumped["viewport"][0] * s == round(jumped["viewport"][0] * s)
    assert notes > 1_000  # the notes under the screen, drawn from those tiles

    assert panned["requested"] == jumped["requested"]  # no new answer asked for
    ty0, ty1 = panned["tilesNear"][1], panned["tilesNear"][3]
    entering = {_tile_path(doc, panned["tiles"], (column, ty)) for ty in range(ty0, ty1 + 1)}
    assert {u.removeprefix(url) for u in after_pan} == entering and len(after_pan) == len(entering)


def test_a_document_opening_zoomed_out_is_asked_tiled_from_its_first_request(speckled, site):
    """Opened at Fit, 40,000 specks are zoomed out: the page's first request is tiled already,
    over HTTP, never a stream answer of aggregates and their masks first. A document whose items
    are drawn themselves at Fit (the far grid) opens on the stream as ever."""
    url, doc, _ = speckled
    _, docs, _ = site
    with chromium_page() as page:
        asked, streams = [], []
        page.on("request", lambda request: asked.append(request.url))
        page.on("websocket", lambda ws: streams.append(ws.url))
        page.goto(f"{url}/?doc={doc}")
        state = _drawn(page, _all_tiles_held())
        views, opened = _views(asked), list(streams)
        asked.clear()
        page.goto(f"{url}/?doc={docs['far']}")
        grid = _drawn(page, "(s) => s.live")
    assert not opened, "a stream opened for a document zoomed out"
    assert views and "/viewport?" in views[0] and all("tiles=true" in u for u in views)
    scales = {float(parse_qs(urlsplit(u).query)["scale"][0]) for u in views}
    assert scales == {state["scale"]} == {ladder_scale(state["tiles"]["z"])}  # on the ladder from the first
    assert state["transport"] == "http" and state["tilesHeld"] and state["aggregates"]
    assert grid["transport"] == "ws" and not grid["tiles"] and len(grid["held"]) == 400
    assert streams and not _views(asked)


def test_the_page_tells_a_refused_token_from_an_unreachable_server_and_names_a_document_not_granted(
    tmp_path,
):
    secret = "s" * 40
    server, url = launch(tmp_path, env={"VANTAGE_TOKENS": "backend", "VANTAGE_JWT_SECRET": secret})
    try:
        backend = {"authorization": "Bearer backend"}
        a, b = (httpx.post(f"{url}/documents", json={"name": n}, headers=backend).json()["id"] for n in "ab")
        httpx.post(
            f"{url}/documents/{a}/items", content=_far_grid(), headers={**backend, **NDJSON}
        ).raise_for_status()
        said = "() => document.getElementById('status').textContent.startsWith('the server')"

        def status(page, path: str) -> tuple[str, str | None]:
            page.goto(f"{url}{path}")
            page.wait_for_function(said, timeout=30_000)
            page.wait_for_timeout(300)  # nothing else is opened after the refusal
            return page.evaluate(
                "() => [document.getElementById('status').textContent, window.vantage.state().doc]"
            )

        reads_a = mint(secret, {a: "read"}, 600)
        with chromium_page() as page:
            assert status(page, f"/?doc={b}#token={reads_a}") == [
                f"the server refused the token (403): the token does not allow reading document {b!r} "
                "(it is not in its `docs`)",
                None,  # not document a, which the token does grant, shown in b's place
            ]
            assert status(page, f"/?doc={a}#token={mint('f' * 40, {a: 'read'}, 600)}") == [
                f"the server refused the token (401): {FORGED}",
                None,
            ]
            assert status(page, f"/?doc={a}") == [
                "the server refused the page without a token (open it as /#token=…) (401): "
                "this needs a token: send `Authorization: Bearer <token>`",
                None,
            ]
            page.route("**/documents", lambda route: route.abort())  # the server is gone
            assert status(page, f"/?doc={a}&again#token={reads_a}") == [
                "the server cannot be reached (Failed to fetch): reload to try again",
                None,
            ]
    finally:
        server.terminate()
        server.communicate(timeout=15)
