"""Zoomed out, an answer drawn as the page draws it (items solid, each aggregate's mask pixel for
pixel) looks like the exact picture of every item: on a document, a clustered board and a field
of specks, at every zoom from page level to the whole scene, within 1% of the screen's pixels
(and no pixel the items ink is left blank); within the entry budget; and after edits."""

import base64

import numpy as np
import orjson
import pytest

from app.answers import View, viewport
from app.items import Item, batch_of
from app.snapshots import build
from app.table import ItemTable
from spatial import scenes
from spatial.overview import TILE
from spatial.raster import pixel_spans

SCREEN = (640, 400)
BUDGET = 5000  # entries per full-HD screen (VANTAGE_LOD_BUDGET)
SCENES = {
    "document": lambda: scenes.long_document(pages=200, seed=1),
    "clustered board": lambda: scenes.clustered_board(n=40_000, seed=2, clusters=60),
    "speck field": lambda: scenes.uniform(n=100_000, seed=3),
}


def _snapshot(boxes: np.ndarray, kinds: np.ndarray):
    names = scenes.KINDS
    bodies = [
        orjson.dumps({"id": f"i{k}", "x0": b[0], "y0": b[1], "x1": b[2], "y1": b[3], "kind": names[c]})
        for k, (b, c) in enumerate(zip(boxes.tolist(), kinds.tolist(), strict=True))
    ]
    table = ItemTable.of([f"i{k}" for k in range(len(boxes))], boxes, bodies)
    return build(table, 1, None)


def _paint(picture: np.ndarray, boxes: np.ndarray, corner, scale: float) -> None:
    """Each box over every pixel it touches, one at least: as the page draws an item."""
    h, w = picture.shape
    c0, c1 = pixel_spans(boxes[:, 0], boxes[:, 2], corner[0], scale)
    r0, r1 = pixel_spans(boxes[:, 1], boxes[:, 3], corner[1], scale)
    for a, b, c, d in zip(
        np.clip(c0, 0, w), np.clip(c1 + 1, 0, w), np.clip(r0, 0, h), np.clip(r1 + 1, 0, h), strict=True
    ):
        picture[c:d, a:b] = True


def _answer_picture(entries: list[dict], corner, scale: float) -> np.ndarray:
    """The answer as the page draws it: items solid, each aggregate's mask cell by cell."""
    picture = np.zeros(SCREEN[::-1], bool)
    items = np.array([[e[k] for k in ("x0", "y0", "x1", "y1")] for e in entries if "agg" not in e]).reshape(
        -1, 4
    )
    _paint(picture, items, corner, scale)
    for entry in (e for e in entries if "agg" in e):
        m = entry["mask"]
        bits = np.unpackbits(np.frombuffer(base64.b64decode(m["bits"]), np.uint8), bitorder="little")
        rows, cols = np.nonzero(bits[: m["w"] * m["h"]].reshape(m["h"], m["w"]))
        x = np.floor((m["x0"] + (cols + 0.5) * m["cell"] - corner[0]) * scale).astype(np.int64)
        y = np.floor((m["y0"] + (rows + 0.5) * m["cell"] - corner[1]) * scale).astype(np.int64)
        keep = (x >= 0) & (x < SCREEN[0]) & (y >= 0) & (y < SCREEN[1])
        picture[y[keep], x[keep]] = True
    return picture


def _scales(boxes: np.ndarray) -> list[float]:
    """From page level down by 2x (a band each) to the scale that fits the whole scene on the screen."""
    extent = boxes[:, 2:].max(axis=0) - boxes[:, :2].min(axis=0)
    fit = float(min(SCREEN[0] / extent[0], SCREEN[1] / extent[1]))
    out, scale = [], 1.0
    while scale > 1.25 * fit:
        out.append(scale)
        scale /= 2
    return [*out, fit]


@pytest.mark.parametrize("scene", SCENES)
def test_every_zoom_draws_within_one_percent_of_the_exact_picture(scene):
    boxes, kinds = SCENES[scene]()
    snap = _snapshot(boxes, kinds)
    rng = np.random.default_rng(7)
    for scale in _scales(boxes):
        for _ in range(3):
            centre = (
                (boxes[rng.integers(len(boxes)), :2] + 0.5)
                if scale > _scales(boxes)[-1]
                else (boxes[:, :2].min(axis=0) + boxes[:, 2:].max(axis=0)) / 2
            )
            half = np.array(SCREEN) / scale / 2
            rect = (*(centre - half).tolist(), *(centre + half).tolist())
            answer = orjson.loads(viewport(snap, View.of(rect, "viewport", scale, 1.0), 100_000, BUDGET))
            exact = np.zeros(SCREEN[::-1], bool)
            inside = (
                (boxes[:, 0] <= rect[2])
                & (boxes[:, 2] >= rect[0])
                & (boxes[:, 1] <= rect[3])
                & (boxes[:, 3] >= rect[1])
            )
            _paint(exact, boxes[inside], rect[:2], scale)
            drawn = _answer_picture(answer["items"], rect[:2], scale)
            where = f"{scene} at 1/{1 / scale:,.0f}, band {answer['band']}"
            assert not (exact & ~drawn).any(), f"{where}: pixels the items ink are left blank"
            assert (exact != drawn).mean() <= 0.01, (
                f"{where}: {(exact != drawn).mean():.2%} of the pixels differ"
            )
            assert len(answer["items"]) <= BUDGET * SCREEN[0] * SCREEN[1] / (1920 * 1080) + 1
            if answer["band"] is not None:  # every aggregate has its mask, of a bounded size
                most = (TILE + 2) * 2.0 ** answer["band"] * scale + 2
                masks = [e["mask"] for e in answer["items"] if "agg" in e]
                assert all(m["w"] <= most and m["h"] <= most for m in masks), where


def test_an_edit_shows_in_the_mask_of_the_aggregate_it_joins():
    boxes, kinds = scenes.clustered_board(n=20_000, seed=4, clusters=20)
    snap = _snapshot(boxes, kinds)
    scale = 1 / 500
    rect = (0.0, 0.0, SCREEN[0] / scale, SCREEN[1] / scale)
    # a note where the board is empty, inside no aggregate: a pixel of its own
    empty = next(
        (x, y)
        for x in range(1000, 1_000_000, 7919)
        for y in (150_000, 400_000)
        if not (
            (boxes[:, 0] <= x + 3000)
            & (boxes[:, 2] >= x - 3000)
            & (boxes[:, 1] <= y + 3000)
            & (boxes[:, 3] >= y - 3000)
        ).any()
    )
    note = Item("added", empty[0], empty[1], empty[0] + 50, empty[1] + 50, "note")
    batch = batch_of([note], 4096)
    edited, _ = snap.with_edits([("added", 2, tuple(batch.boxes[0].tolist()), batch.bodies[0])])
    before = _answer_picture(
        orjson.loads(viewport(snap, View.of(rect, "v", scale, 1.0), 100_000, BUDGET))["items"],
        rect[:2],
        scale,
    )
    after = _answer_picture(
        orjson.loads(viewport(edited, View.of(rect, "v", scale, 1.0), 100_000, BUDGET))["items"],
        rect[:2],
        scale,
    )
    px, py = int((empty[0] - rect[0]) * scale), int((empty[1] - rect[1]) * scale)
    assert not before[py, px] and after[py, px]
    deleted, _ = edited.with_edits([("added", 3, None, None)])
    gone = _answer_picture(
        orjson.loads(viewport(deleted, View.of(rect, "v", scale, 1.0), 100_000, BUDGET))["items"],
        rect[:2],
        scale,
    )
    assert not gone[py, px]


def test_a_pan_by_whole_pixels_keeps_the_masks_held_and_any_other_move_sends_them_again():
    from app.answers import Held, change

    boxes, kinds = scenes.clustered_board(n=40_000, seed=2, clusters=60)
    snap = _snapshot(boxes, kinds)
    scale = 1 / 300
    start = (300_000.0, 300_000.0, 300_000.0 + SCREEN[0] / scale, 300_000.0 + SCREEN[1] / scale)

    def answer(rect):
        return {
            e["id"]: e
            for e in orjson.loads(viewport(snap, View.of(rect, "v", scale, 1.0), 100_000, BUDGET))["items"]
        }

    def pan(rect, pixels):
        return tuple(v + pixels / scale for v in rect)

    held = answer(start)
    shown = change(snap, View.of(start, "v", scale, 1.0), None, 100_000, BUDGET).shown
    for pixels, resent in ((37, False), (0.4, True)):
        moved = pan(start, pixels)
        diff = change(snap, View.of(moved, "v", scale, 1.0), Held(shown, 1, snap), 100_000, BUDGET)
        entered = {e["id"] for e in orjson.loads(diff.enter)}
        after = answer(moved)
        staying = {i for i in after if i.startswith("~")} & set(held)
        assert staying, "no aggregate stays: the pan is too long for the test"
        assert bool(staying & entered) == resent  # sent again only when the grid moved
        if not resent:  # held masks are the new answer's, byte for byte
            assert all(held[i] == after[i] for i in staying)


def test_an_answers_masks_stop_at_their_pixel_budget(monkeypatch):
    """However big a viewport a client asks for, its masks cover a bounded number of pixels;
    the aggregates past it come without one (drawn as their boxes)."""
    import app.masks

    monkeypatch.setattr(app.masks, "MAX_ANSWER_MASK_PIXELS", 20_000)
    boxes, kinds = scenes.uniform(n=100_000, seed=3)
    snap = _snapshot(boxes, kinds)
    rect = (0.0, 0.0, 20_000.0, 20_000.0)  # at scale 1/16: 1,250 x 1,250 pixels
    entries = orjson.loads(viewport(snap, View.of(rect, "v", 1 / 16, 1.0), 100_000, None))["items"]
    aggregates = [e for e in entries if "agg" in e]
    masked = [e["mask"] for e in aggregates if "mask" in e]
    assert masked and len(masked) < len(aggregates)
    assert sum(m["w"] * m["h"] for m in masked) <= 20_000
