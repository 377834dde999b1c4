"""Zoomed out, masks are kept and tiles made once: every kept answer is the answer made afresh,
byte for byte, through pans, zooms and edits; a tile holds exactly the band's aggregates touching
it, its bitmaps exactly their masks, and every small item's pixels (brute force); an edit remakes
exactly the tiles it touches, and no answer or tile shows a stale one, in one process, across
workers and on PostgreSQL; the tile URL caches as HTTP says, within the access rules."""

import base64
import zlib

import httpx
import numpy as np
import orjson
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from service import NDJSON, client, item_json, ndjson, spawn_server
from test_masks import _snapshot

from app.answers import Held, View, change, shown, viewport
from app.masks import masks
from app.tiles import TILE_PIXELS, TileKey, Tiles, ladder_level, ladder_scale, tile_changed_since, tile_keys
from spatial import scenes
from spatial.raster import pixel_spans

BUDGET, CAP = 5000, 10_000
SCREEN = (640, 400)


BOARD = scenes.clustered_board(n=8000, seed=7, clusters=40)


@pytest.fixture
def board():
    """A fresh snapshot: edits share the tree's buffers with the snapshot they are made from,
    so two histories never branch from one."""
    boxes, kinds = BOARD
    return _snapshot(boxes, kinds), boxes, kinds


def _fit(boxes: np.ndarray) -> float:
    x0, y0 = boxes[:, :2].min(0)
    x1, y1 = boxes[:, 2:].max(0)
    return float(min(SCREEN[0] / (x1 - x0), SCREEN[1] / (y1 - y0)))


def _view(boxes: np.ndarray, at: int, scale: float, shift=(0, 0)) -> View:
    cx, cy = (boxes[at, :2] + boxes[at, 2:]) / 2
    hw, hh = SCREEN[0] / scale / 2, SCREEN[1] / scale / 2
    dx, dy = shift[0] / scale, shift[1] / scale  # whole pixels
    rect = (float(cx - hw + dx), float(cy - hh + dy), float(cx + hw + dx), float(cy + hh + dy))
    return View.of(rect, "view", scale, 1.0)


STEPS = st.lists(
    st.tuples(
        st.sampled_from(["look", "pan", "move", "delete"]),
        st.integers(0, 7999),
        st.floats(0.0, 1.0),
        st.integers(-300, 300),
    ),
    min_size=3,
    max_size=12,
)


@settings(max_examples=20, deadline=None)
@given(steps=STEPS)
def test_answers_with_masks_kept_are_the_answers_made_afresh(steps):
    """Views at every zoom from the whole board in, whole-pixel pans, and edits between: with
    the kept masks, every /viewport and /diff answer equals the one made with none kept."""
    boxes, kinds = BOARD
    snap = _snapshot(boxes, kinds)
    kept = Tiles()
    fit = _fit(boxes)
    view = _view(boxes, 0, fit)
    version = snap.version
    for kind, at, zoom, pixels in steps:
        if kind == "move":
            box = boxes[at] + np.array([pixels, -pixels, pixels, -pixels]) * 3.0
            version += 1
            snap, _ = snap.with_edits(
                [(f"i{at}", version, tuple(box), item_json(f"i{at}", box, kind="note"))]
            )
            continue
        if kind == "delete":
            version += 1
            snap, _ = snap.with_edits([(f"i{at}", version, None, None)])
            continue
        old = view
        scale = fit * 2 ** (zoom * 6) if kind == "look" else view.scale
        view = _view(boxes, at, scale) if kind == "look" else _view(boxes, at, scale, (pixels, pixels // 2))
        afresh = viewport(snap, view, CAP, BUDGET)
        assert viewport(snap, view, CAP, BUDGET, kept) == afresh
        assert viewport(snap, view, CAP, BUDGET, kept) == afresh  # asked again: from what was kept
        held = Held(shown(snap, old, CAP, BUDGET), snap.version)
        assert (
            change(snap, view, held, CAP, BUDGET, kept).json() == change(snap, view, held, CAP, BUDGET).json()
        )


def test_an_edited_aggregate_never_shows_its_kept_mask(board):
    """The same screen before and after edits in it (moves, a deletion): its masks were kept
    before; after, every answer equals the one made afresh."""
    snap, boxes, _ = board
    kept = Tiles()
    view = _view(boxes, 100, _fit(boxes) * 8)
    viewport(snap, view, CAP, BUDGET, kept)
    x0, y0, x1, y1 = view.rect
    inside = np.flatnonzero(
        (boxes[:, 0] >= x0) & (boxes[:, 2] <= x1) & (boxes[:, 1] >= y0) & (boxes[:, 3] <= y1)
    )
    assert len(inside) > 20
    step = (x1 - x0) / SCREEN[0] * 7  # seven pixels
    for k, at in enumerate(inside[:: len(inside) // 10][:10].tolist()):
        if k % 3 == 2:
            snap, _ = snap.with_edits([(f"i{at}", snap.version + 1, None, None)])
        else:
            box = boxes[at] + np.array([step, step, step, step])
            snap, _ = snap.with_edits(
                [(f"i{at}", snap.version + 1, tuple(box), item_json(f"i{at}", box, kind="note"))]
            )
        assert viewport(snap, view, CAP, BUDGET, kept) == viewport(snap, view, CAP, BUDGET)


def _layers(body: dict) -> dict[str, np.ndarray]:
    size = body["size"]
    return {
        name: np.unpackbits(
            np.frombuffer(zlib.decompress(base64.b64decode(bits)), np.uint8), bitorder="little"
        ).reshape(size, size)
        for name, bits in body["layers"].items()
    }


def _tiles_of(snap, boxes, scale):
    """The tiles of the band the whole board is answered at, on the rung nearest ``scale``."""
    z = ladder_level(scale)
    s = ladder_scale(z)
    band = shown(snap, _view(boxes, 0, s), CAP, BUDGET).band
    x0, y0 = boxes[:, :2].min(0)
    x1, y1 = boxes[:, 2:].max(0)
    return band, z, list(tile_keys(band, z, (float(x0), float(y0), float(x1), float(y1))))


@pytest.mark.parametrize("zoom", [1.0, 4.0, 16.0])
def test_a_tile_is_the_masks_of_the_aggregates_touching_it(board, zoom):
    snap, boxes, _kinds = board
    overview = snap.overview
    band, z, keys = _tiles_of(snap, boxes, _fit(boxes) * zoom)
    scale = ladder_scale(z)
    everyone = np.arange(overview.built(band))
    every_box, count, cover, kind, _ = overview.rows(band, everyone)
    threshold = overview.threshold(band)
    small = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]) < threshold
    kept = Tiles()
    inked = 0
    for key in keys:
        body = orjson.loads(kept.tile(snap, key).body)
        x0, y0, x1, y1 = key.rect
        touching = everyone[
            (every_box[:, 0] <= x1)
            & (every_box[:, 2] >= x0)
            & (every_box[:, 1] <= y1)
            & (every_box[:, 3] >= y0)
        ]
        aggs = body["aggregates"]
        assert sorted(aggs["index"]) == touching.tolist()  # brute force over the band
        at = np.array(aggs["index"], np.int64)
        assert aggs["count"] == count[at].tolist()
        assert aggs["cover"] == np.rint(cover[at] * 1000).astype(int).tolist()
        assert aggs["kind"] == [snap.looks.names[k] for k in kind[at].tolist()]
        # the bitmaps: each kind's layer is its aggregates' masks, in the rung's own pixel grid
        expected = {}
        shapes = masks(snap, band, at, (scale, 0, 0))
        for _index, k, shape in zip(at.tolist(), kind[at].tolist(), shapes, strict=True):
            if not shape:
                continue
            mask = orjson.loads(b"{" + shape + b"}")["mask"]
            bits = np.unpackbits(
                np.frombuffer(base64.b64decode(mask["bits"]), np.uint8),
                count=mask["w"] * mask["h"],
                bitorder="little",
            ).reshape(mask["h"], mask["w"])
            c0 = round(mask["x0"] * scale) - key.tx * TILE_PIXELS
            r0 = round(mask["y0"] * scale) - key.ty * TILE_PIXELS
            layer = expected.setdefault(snap.looks.names[k], np.zeros((TILE_PIXELS, TILE_PIXELS), np.uint8))
            ys, xs = np.nonzero(bits)
            inside = (xs + c0 >= 0) & (xs + c0 < TILE_PIXELS) & (ys + r0 >= 0) & (ys + r0 < TILE_PIXELS)
            layer[ys[inside] + r0, xs[inside] + c0] = 1
        layers = _layers(body)
        assert {k: v for k, v in expected.items() if v.any()}.keys() == layers.keys()
        for name, layer in layers.items():
            assert np.array_equal(layer, expected[name]), name
        # brute force: every small item's pixels in the tile are inked in some layer
        union = np.zeros((TILE_PIXELS, TILE_PIXELS), bool)
        for layer in layers.values():
            union |= layer.astype(bool)
        mine = small & (boxes[:, 0] <= x1) & (boxes[:, 2] >= x0) & (boxes[:, 1] <= y1) & (boxes[:, 3] >= y0)
        c0, c1 = pixel_spans(boxes[mine, 0], boxes[mine, 2], x0, scale)
        r0, r1 = pixel_spans(boxes[mine, 1], boxes[mine, 3], y0, scale)
        for a, b, c, d in zip(c0.tolist(), c1.tolist(), r0.tolist(), r1.tolist(), strict=True):
            window = union[max(c, 0) : min(d, TILE_PIXELS - 1) + 1, max(a, 0) : min(b, TILE_PIXELS - 1) + 1]
            assert window.size == 0 or window.all(), (key, a, c)
        inked += int(union.sum())
    assert inked > 0


def test_an_edit_remakes_exactly_the_tiles_it_touches(board):
    snap, boxes, _ = board
    _band, _z, keys = _tiles_of(snap, boxes, _fit(boxes) * 4)
    kept = Tiles()
    before = {key: kept.tile(snap, key) for key in keys}
    at = int(np.argmax(boxes[:, 0]))  # an item at the board's edge, moved into its middle
    box = (boxes[:, :2].mean(0).tolist() * 2)[:2] + (boxes[:, :2].mean(0) + 1.0).tolist()
    edited, _ = snap.with_edits(
        [(f"i{at}", snap.version + 1, tuple(box), item_json(f"i{at}", box, kind="note"))]
    )
    touched = {key for key in keys if tile_changed_since(edited, key, snap.version)}
    assert 0 < len(touched) < len(keys)
    for key in keys:
        tile = kept.tile(edited, key)
        fresh = Tiles().tile(edited, key)
        assert tile.body == fresh.body  # never stale
        assert (tile is before[key]) == (key not in touched)  # the others are shared
        if tile.body != before[key].body:
            assert key in touched


def test_the_cache_keeps_to_its_budget(board):
    snap, boxes, _ = board
    kept = Tiles(most=400_000)
    fit = _fit(boxes)
    for k in range(30):
        view = _view(boxes, k * 97, fit * 2 ** (k % 6))
        viewport(snap, view, CAP, BUDGET, kept)
        kept.answer(snap, ("viewport", view), lambda view=view: viewport(snap, view, CAP, BUDGET, kept))
        _band, _z, keys = _tiles_of(snap, boxes, fit * 2 ** (k % 4))
        kept.tile(snap, keys[k % len(keys)])
        assert kept.nbytes <= kept.most + 120_000  # at most the newest, past it
    assert kept.stats()["held"] < kept.made


def _scene_ndjson():
    boxes, kinds = scenes.clustered_board(n=4000, seed=3, clusters=20)
    return boxes, kinds, ndjson(boxes, kinds)


def _tiled(c, doc, boxes, scale, **extra):
    x0, y0 = boxes[:, :2].min(0)
    x1, y1 = boxes[:, 2:].max(0)
    params = {"x0": x0, "y0": y0, "x1": x1, "y1": y1, "scale": scale, "min_px": 1, "tiles": "true", **extra}
    return c.get(f"/documents/{doc}/viewport", params=params)


def test_the_tile_url_caches_as_http_says(tmp_path, monkeypatch):
    monkeypatch.setenv("VANTAGE_DATA_DIR", str(tmp_path))
    boxes, _, body = _scene_ndjson()
    with client() as c:
        doc = c.post("/documents", json={"name": "board"}).json()["id"]
        assert c.post(f"/documents/{doc}/items", content=body, headers=NDJSON).status_code == 200
        answer = _tiled(c, doc, boxes, ladder_scale(ladder_level(_fit(boxes)))).json()
        sheet, version = answer["tiles"], answer["version"]
        assert answer["band"] is not None and sheet["band"] == answer["band"] and answer["aggregates"] > 0
        assert not any(e["id"].startswith("~") for e in answer["items"])  # left to the tiles
        tx0, ty0, _tx1, _ty1 = sheet["range"]
        url = f"/documents/{doc}/tiles/{sheet['band']}/{sheet['z']}/{tx0}/{ty0}"
        tile = c.get(url, params={"version": version}, headers={"accept-encoding": "gzip"})
        assert tile.status_code == 200 and tile.headers["content-encoding"] == "gzip"
        assert tile.headers["cache-control"] == "public, max-age=31536000, immutable"
        assert tile.json()["band"] == sheet["band"] and tile.json()["size"] == TILE_PIXELS
        etag = tile.headers["etag"]
        again = c.get(url, headers={"if-none-match": etag})
        assert again.status_code == 304 and again.content == b"" and again.headers["etag"] == etag
        assert again.headers["cache-control"] == "public, no-cache"
        assert c.get(url, headers={"if-none-match": '"other"'}).status_code == 200
        # an edit that changes the tile: its old version's URL is a 409, naming the new one
        x0, y0, x1, y1 = TileKey(sheet["band"], sheet["z"], tx0, ty0).rect
        inside = np.flatnonzero(
            (boxes[:, 0] >= x0) & (boxes[:, 2] <= x1) & (boxes[:, 1] >= y0) & (boxes[:, 3] <= y1)
        )
        if len(inside):
            gone = c.delete(f"/documents/{doc}/items/i{inside[0]}")
            assert gone.status_code in (200, 204), gone.text
            stale = c.get(url, params={"version": version})
            assert stale.status_code == 409 and f"ask at version {version + 1}" in stale.json()["detail"]
            fresh = c.get(url, params={"version": version + 1})
            assert fresh.status_code == 200 and fresh.headers["etag"] != etag
        for bad, words in [
            (f"/documents/{doc}/tiles/99/0/0/0", "band 99: this document's bands are"),
            (f"/documents/{doc}/tiles/{sheet['band']}/100000/0/0", "z=100000: the tiles of band"),
            (
                f"/documents/{doc}/tiles/{sheet['band']}/{sheet['z']}/{2**60}/0",
                "past the canvas's float range",
            ),
        ]:
            refused = c.get(bad)
            assert refused.status_code in (404, 422) and words in refused.json()["detail"], refused.text
        assert c.get(f"/documents/nope/tiles/{sheet['band']}/{sheet['z']}/0/0").status_code == 404


def test_a_tile_needs_the_token_a_read_needs(tmp_path, monkeypatch):
    monkeypatch.setenv("VANTAGE_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("VANTAGE_TOKENS", "s3cret")
    monkeypatch.setenv("VANTAGE_READ_TOKEN", "true")
    good = {"authorization": "Bearer s3cret"}
    boxes, _, body = _scene_ndjson()
    with client() as c:
        doc = c.post("/documents", json={"name": "board"}, headers=good).json()["id"]
        c.post(f"/documents/{doc}/items", content=body, headers={**NDJSON, **good})
        sheet = _tiled(c, doc, boxes, _fit(boxes), token="s3cret").json()["tiles"]
        url = f"/documents/{doc}/tiles/{sheet['band']}/{sheet['z']}/{sheet['range'][0]}/{sheet['range'][1]}"
        assert c.get(url).status_code == 401
        assert c.get(url, headers={"authorization": "Bearer nope"}).status_code == 403
        tile = c.get(url, headers=good)
        assert tile.status_code == 200 and tile.headers["cache-control"].startswith("private, ")


@pytest.mark.slow(seconds=25)
@pytest.mark.parametrize("store", ["sqlite", "postgres"])
def test_no_worker_serves_a_stale_tile_after_an_edit(store, tmp_path, request):
    """Two workers (each with its own tiles), an edit through one: every tile either shows it
    or was not touched by it, whichever worker answers, on either store."""
    env = None
    if store == "postgres":
        env = {"VANTAGE_DATABASE_URL": request.getfixturevalue("postgres").new_database("tiles")}
    process, url = spawn_server(tmp_path, "--workers", "2", env=env)
    try:
        boxes, _, body = _scene_ndjson()
        doc = httpx.post(f"{url}/documents", json={"name": "board"}).json()["id"]
        httpx.post(
            f"{url}/documents/{doc}/items", content=body, headers=NDJSON, timeout=60
        ).raise_for_status()
        scale = ladder_scale(ladder_level(_fit(boxes) * 2))
        params = {"scale": scale, "min_px": 1, "tiles": "true"}

        def tiles(version):
            x0, y0 = boxes[:, :2].min(0)
            x1, y1 = boxes[:, 2:].max(0)
            answers = []
            for _ in range(4):  # new connections: both workers answer
                with httpx.Client(base_url=url) as one:
                    answer = one.get(
                        f"/documents/{doc}/viewport",
                        params={**params, "x0": x0, "y0": y0, "x1": x1, "y1": y1, "min_version": version},
                    ).json()
                    sheet = answer["tiles"]
                    tx0, ty0, tx1, ty1 = sheet["range"]
                    got = {
                        (tx, ty): one.get(
                            f"/documents/{doc}/tiles/{sheet['band']}/{sheet['z']}/{tx}/{ty}",
                            params={"version": answer["version"]},
                        ).json()
                        for tx in range(tx0, tx1 + 1)
                        for ty in range(ty0, ty1 + 1)
                    }
                    answers.append((answer["version"], got))
            return answers

        before = tiles(1)
        at = int(np.argmin(boxes[:, 0]))
        middle = boxes[:, :2].mean(0) - boxes[at, :2]  # from the board's edge to its middle
        moved = (boxes[at] + np.concatenate([middle, middle])).tolist()
        edit = httpx.put(
            f"{url}/documents/{doc}/items/i{at}",
            content=item_json(f"i{at}", moved, kind="note"),
            headers={"content-type": "application/json"},
        )
        assert edit.status_code == 200, edit.text
        after = tiles(2)
        assert all(version == 2 for version, _ in after)
        first = after[0][1]
        assert all(got == first for _, got in after)  # every worker answers the same tiles
        changed = [k for k in first if first[k] != before[0][1].get(k)]
        assert changed  # the edit shows
        # the moved item's pixel is inked where it is now, whichever worker answers
        rung = ladder_scale(ladder_level(scale))
        column, row = int(np.floor(moved[0] * rung)), int(np.floor(moved[1] * rung))
        tile = first[column // TILE_PIXELS, row // TILE_PIXELS]
        union = sum(layer.astype(int) for layer in _layers(tile).values())
        assert union[row % TILE_PIXELS, column % TILE_PIXELS] > 0
    finally:
        process.terminate()
        process.communicate(timeout=30)
