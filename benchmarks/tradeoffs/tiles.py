"""Trade 6, zoomed out, part two: tiles against answers made for each screen.

Every zoomed-out answer is measured as the service makes it (``app.answers`` on a built
snapshot): made for its screen (its masks in the screen's own pixels: the exact picture's
pixels), again with the masks kept (another client, the same view), and from tiles, which a
page keeps and a CDN can serve. Tiles are made on a ladder of scales (``app.tiles``): drawn at
a ladder scale with pixel lines on the canvas's, their bitmaps fall on the screen's pixels; drawn
at a scale between two rungs (a page that does not snap its zoom), each tile pixel inks every
screen pixel it touches, and the picture grows by a fraction of a pixel around what it draws.
Reported: pixels off against the exact picture, bytes a screen and CPU per answer."""

from __future__ import annotations

import base64
import gc
import gzip
import math
import time
import zlib
from dataclasses import dataclass

import numpy as np
import orjson

from app.answers import View, viewport
from app.snapshots import Snapshot, build
from app.table import ItemTable
from app.tiles import Tiles, ladder_level, ladder_scale, tile_keys
from spatial import Rect, scenes

from .aggregates import AGG_GOAL, AGG_MIN_PX, agg_scales, agg_views, scale_name, service_budget
from .render import SCREEN, render
from .report import kb, md_table, pct
from .scene import Scene

TILE_REPEAT = 5  # answers asked again, timed per view
MODES = ("screen", "screen, kept", "tiles, on the ladder", "tiles, between rungs")
# A tile pixel's box is drawn shrunk by this share of a screen pixel on each side: an edge on a
# pixel line inks one side only, as the page's whole-pixel drawing does.
_SLIVER = 1 / 400


@dataclass
class TileRow:
    scene: Scene
    scale: float
    fit: bool
    mode: str
    error: np.ndarray  # (views,) share of the screen's pixels differing from the exact picture
    blank: int  # pixels the exact picture draws and this one leaves blank, over the views
    wire: np.ndarray  # (views,) bytes a screen costs gzipped: the answer, or a tiled answer and its tiles
    tiles: np.ndarray  # (views,) tiles a screen needs (0: none)
    ms: float  # p50 per answer: made (screen), asked again (kept), the tiled answer (tiles)
    made_ms: float  # p50 per screen of making what it needs, nothing kept: masks, or its tiles


def snapshot_of(scene: Scene) -> Snapshot:
    """The scene as the service holds it: items with their kinds, built as an import builds."""
    names = scenes.KINDS
    bodies = [
        orjson.dumps({"id": f"i{k}", "x0": b[0], "y0": b[1], "x1": b[2], "y1": b[3], "kind": names[c]})
        for k, (b, c) in enumerate(zip(scene.boxes.tolist(), scene.kinds.tolist(), strict=True))
    ]
    table = ItemTable.of([f"i{k}" for k in range(len(scene.boxes))], scene.boxes, bodies)
    return build(table, 1, None)


def _items_and_masks(body: dict) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """An answer's entries as boxes and kinds: items as their boxes, an aggregate's mask
    pixels each as its box, an aggregate without a mask as its box."""
    boxes, kinds = [], []
    for entry in body["items"]:
        kind = scenes.KINDS.index(entry["kind"])
        mask = entry.get("mask")
        if mask is None:
            boxes.append(np.array([[entry["x0"], entry["y0"], entry["x1"], entry["y1"], 0.0]]))
            kinds.append(np.array([kind]))
            continue
        w, h, cell = mask["w"], mask["h"], mask["cell"]
        bits = np.unpackbits(
            np.frombuffer(base64.b64decode(mask["bits"]), np.uint8), count=w * h, bitorder="little"
        )
        rows, cols = np.divmod(np.flatnonzero(bits), w)
        boxes.append(_pixel_boxes(mask["x0"] + cols * cell, mask["y0"] + rows * cell, cell))
        kinds.append(np.full(len(cols), kind))
    return boxes, kinds


def _pixel_boxes(x0: np.ndarray, y0: np.ndarray, cell: float) -> np.ndarray:
    """Mask or tile pixels as boxes, marked by a NaN fifth column: drawn a sliver smaller."""
    return np.stack([x0, y0, x0 + cell, y0 + cell, np.full(len(x0), np.nan)], axis=1)


def _tile_boxes(body: dict) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A tile's layers' pixels and its boxed aggregates, as boxes and kinds."""
    scale, size = body["scale"], body["size"]
    c0, r0 = body["tx"] * size, body["ty"] * size
    boxes, kinds = [], []
    for name, layer in body["layers"].items():
        bits = np.unpackbits(
            np.frombuffer(zlib.decompress(base64.b64decode(layer)), np.uint8), bitorder="little"
        )
        rows, cols = np.divmod(np.flatnonzero(bits), size)
        boxes.append(_pixel_boxes((c0 + cols) / scale, (r0 + rows) / scale, 1 / scale))
        kinds.append(np.full(len(cols), scenes.KINDS.index(name)))
    aggs = body["aggregates"]
    for at in aggs["boxed"]:
        c = aggs["box"][4 * at : 4 * at + 4]
        boxes.append(
            np.array(
                [[(c0 + c[0]) / scale, (r0 + c[1]) / scale, (c0 + c[2]) / scale, (r0 + c[3]) / scale, 0.0]]
            )
        )
        kinds.append(np.array([scenes.KINDS.index(aggs["kind"][at])]))
    return boxes, kinds


def _draw(boxes: list[np.ndarray], kinds: list[np.ndarray], rect: Rect, scale: float) -> np.ndarray:
    """The boxes drawn as the page draws them: each over every pixel it touches (mask and tile
    pixels a sliver smaller), kinds in z order."""
    if not boxes:
        return render(np.empty((0, 4)), np.empty(0, np.uint8), rect, scale)
    every = np.concatenate(boxes).astype(float)
    pixels = np.isnan(every[:, 4])
    every = every[:, :4]
    sliver = _SLIVER / scale
    every[pixels, :2] += sliver
    every[pixels, 2:] -= sliver
    return render(every, np.concatenate(kinds), rect, scale)


def _on_ladder(rect: Rect, scale: float) -> tuple[Rect, float]:
    """The view a page snapping to the ladder draws: the nearest rung, about the same centre,
    its corner on the rung's pixel lines."""
    s = ladder_scale(ladder_level(scale))
    cx, cy = (rect[0] + rect[2]) / 2, (rect[1] + rect[3]) / 2
    x0, y0 = math.floor((cx - SCREEN[0] / 2 / s) * s) / s, math.floor((cy - SCREEN[1] / 2 / s) * s) / s
    return (x0, y0, x0 + SCREEN[0] / s, y0 + SCREEN[1] / s), s


def trade_tiles(scene: Scene, seed: int) -> list[TileRow]:
    snap = snapshot_of(scene)
    budget, cap = service_budget()
    rows = []
    for scale, fit in agg_scales(scene.boxes):
        rects = agg_views(scene, scale, fit, seed)
        stats = {mode: [np.zeros(len(rects)) for _ in range(3)] + [0, [], []] for mode in MODES}
        for v, rect in enumerate(rects):
            ladder_rect, rung = _on_ladder(rect, scale)
            for mode in MODES:
                error, wire, needed, _, ms, made = stats[mode]
                at_scale, at_rect = (rung, ladder_rect) if mode == "tiles, on the ladder" else (scale, rect)
                view = View.of(at_rect, "view", at_scale, AGG_MIN_PX)
                kept = None if mode == "screen" else Tiles(1 << 40)
                tiled = mode.startswith("tiles")
                t0 = time.perf_counter()
                answer = viewport(snap, view, cap, budget, kept, tiled=tiled)
                if not tiled:
                    made.append(time.perf_counter() - t0)
                sheet = orjson.loads(answer).get("tiles")  # between rungs: the nearest rung's
                for _ in range(TILE_REPEAT if mode != "screen" else 0):
                    t0 = time.perf_counter()
                    viewport(snap, view, cap, budget, kept, tiled=tiled)
                    ms.append(time.perf_counter() - t0)
                if mode == "screen":
                    ms.append(made[-1])
                body = orjson.loads(answer)
                boxes, kinds = _items_and_masks(body)
                wire[v] = len(gzip.compress(answer, 6))
                if tiled and sheet is not None:
                    assert kept is not None
                    keys = list(tile_keys(sheet["band"], sheet["z"], view.rect))
                    t0 = time.perf_counter()
                    bodies = [kept.tile(snap, key) for key in keys]
                    made.append(time.perf_counter() - t0)
                    wire[v] += sum(len(t.gzipped) for t in bodies)
                    needed[v] = len(keys)
                    for t in bodies:
                        more, more_kinds = _tile_boxes(orjson.loads(t.body))
                        boxes += more
                        kinds += more_kinds
                truth_ids = scene.tree.query(view.rect)
                truth = render(scene.boxes[truth_ids], scene.kinds[truth_ids], view.rect, at_scale)
                drawn = _draw(boxes, kinds, view.rect, at_scale)
                error[v] = np.count_nonzero(drawn != truth) / truth.size
                stats[mode][3] += int(np.count_nonzero((truth > 0) & (drawn == 0)))
        for mode in MODES:
            error, wire, needed, blank, ms, made = stats[mode]
            p50 = lambda times: float(np.median(times)) * 1e3 if times else 0.0
            rows.append(TileRow(scene, scale, fit, mode, error, blank, wire, needed, p50(ms), p50(made)))
    del snap
    gc.collect()
    return rows


def section_tiles(rows: list[TileRow]) -> list[str]:
    """The table: for each scene and scale, the four ways side by side."""
    out = [
        "### Tiles against answers made for each screen",
        "",
        "Each zoomed-out screen as the service answers it (`app.answers.viewport` on a built snapshot, "
        f"{service_budget()[0]:,} entries a screen), drawn as the page draws it, against the exact "
        "picture. *screen*: the answer made for the screen (its masks in the screen's pixels); *kept*: "
        "the same asked again, its masks kept; *tiles, on the ladder*: a page snapping its zoom to the "
        "nearest rung of the ladder (2^(-z/4) pixels a unit) and its corner to the rung's pixels, taking "
        "the tiled answer and its tiles; *between rungs*: the nearest rung's tiles drawn at the screen's "
        "own scale, each tile pixel over every screen pixel it touches. Pixels off: the median and worst "
        f"share of the screen (the goal: {pct(AGG_GOAL[0], 0)}); left blank: pixels the exact picture "
        "draws that this one does not, over the views (none, by design). KB a screen: gzipped, the answer "
        "plus every tile it names (a page holding them pays only the answer). ms: p50 in-process per "
        "answer (screen: made; kept and tiles: asked again); made: p50 per screen of making what it "
        "needs with nothing kept (masks, or the screen's tiles).",
        "",
    ]
    body = [
        [
            r.scene.title,
            scale_name(r.scale, r.fit),
            r.mode,
            f"{pct(float(np.median(r.error)), 2)} / {pct(float(r.error.max()), 2)}",
            str(r.blank),
            kb(float(np.median(r.wire))),
            f"{np.median(r.tiles):.0f}" if r.tiles.any() else "—",
            f"{r.ms:.2f}",
            f"{r.made_ms:.1f}",
        ]
        for r in rows
    ]
    out += md_table(
        [
            "scene",
            "scale",
            "answer",
            "pixels off p50 / max",
            "left blank",
            "KB a screen",
            "tiles",
            "ms",
            "made ms",
        ],
        body,
        "lllrrrrrr",
    )
    return [*out, ""]
