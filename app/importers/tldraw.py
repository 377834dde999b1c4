"""tldraw documents (``.tldr``, tldraw 2 and later: ``{"tldrawFileFormatVersion": 1, "records":
[...]}``). Each shape record becomes an item: its id, ``kind`` its type, its box the bounds
on the page of its geometry, placed by its ``x``, ``y`` and ``rotation`` (radians, about its
top-left corner) after those of the frames and groups it sits in; ``z`` its place in the
page's drawing order (siblings by fractional ``index``). Geometry: ``props.w`` by ``props.h``
(plus ``growY``); a note is 200 square; a line, arrow or stroke is bounded by its points; a
group by its children; text is ``props.w`` wide and a line of its font size (1.35 times it)
per line of text. Pages after the first are placed to the right of the one before."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .base import ImportFailed, Matrix, Source, apply, bounds, compose, json_of

__all__ = ["NAME", "SUFFIXES", "detect", "read"]

NAME = "tldraw"
SUFFIXES = (".tldr",)
FONT_SIZES = {"s": 18, "m": 24, "l": 36, "xl": 44}
LINE_HEIGHT = 1.35
NOTE_SIZE = 200.0
PAGE_GAP = 200.0


def detect(path: Path, head: bytes) -> bool:
    return path.suffix.lower() in SUFFIXES or b'"tldrawFileFormatVersion"' in head


def read(source: Source) -> Iterator[tuple[str, dict]]:
    document = json_of(source, "save the document again from tldraw")
    if isinstance(document, dict) and "document" in document and "records" not in document:
        raise ImportFailed("a tldraw 1 file: open it in tldraw (2 or later) and save it again")
    if not isinstance(document, dict) or not isinstance(document.get("records"), list):
        raise ImportFailed(
            'not a tldraw document: one is {"tldrawFileFormatVersion": 1, "records": [...]}; save it '
            "from tldraw's menu (Save a copy)"
        )
    records = [r for r in document["records"] if isinstance(r, dict)]
    pages = sorted((r for r in records if r.get("typeName") == "page"), key=lambda r: str(r.get("index", "")))
    shapes = {r.get("id"): r for r in records if r.get("typeName") == "shape"}
    children: dict[Any, list[dict]] = {}
    for shape in shapes.values():
        children.setdefault(shape.get("parentId"), []).append(shape)
    for siblings in children.values():
        siblings.sort(key=lambda s: str(s.get("index", "")))
    layout = _Layout(shapes, children)
    right: float | None = None
    for page in pages:
        placed = layout.page(page["id"])
        if not placed:
            continue
        left = min(item["x0"] for item in placed)
        dx = 0.0 if right is None else right + PAGE_GAP - left
        for item in placed:
            item["x0"] += dx
            item["x1"] += dx
            if len(pages) > 1:
                item.setdefault("data", {})["page"] = page.get("name", page["id"])
        right = max(item["x1"] for item in placed)
        yield from ((f"shape {item['id']!r}", item) for item in placed)
    source.done = source.size


class _Layout:
    def __init__(self, shapes: dict[Any, dict], children: dict[Any, list[dict]]) -> None:
        self.shapes, self.children = shapes, children

    def page(self, page_id: str) -> list[dict]:
        """The page's shapes as items, in drawing order."""
        out: list[dict] = []
        for shape in self.children.get(page_id, []):
            self._place(shape, (1.0, 0.0, 0.0, 1.0, 0.0, 0.0), out, 0)
        for z, item in enumerate(out):  # pre-order: a frame or group under what it holds
            item["z"] = z
        return out

    def _place(self, shape: dict, parent: Matrix, out: list[dict], depth: int) -> tuple | None:
        """Append ``shape`` and its descendants to ``out``; the shape's page bounds."""
        where = f"shape {shape.get('id')!r}"
        if depth > 100:
            raise ImportFailed(f"{where}: nested more than 100 deep (a parent loop?): fix its parentId")
        try:
            x, y = float(shape.get("x", 0.0)), float(shape.get("y", 0.0))
            matrix = compose(parent, _local(x, y, float(shape.get("rotation") or 0.0)))
            item = {"id": shape["id"], "kind": shape["type"], "z": 0}
            text = _text(shape.get("props") or {})
            if text:
                item["data"] = {"text": text}
            out.append(item)
            inside = [
                self._place(child, matrix, out, depth + 1) for child in self.children.get(shape["id"], [])
            ]
            points = _geometry(shape, [b for b in inside if b is not None])
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            why = f"no {error.args[0]!r}" if isinstance(error, KeyError) else str(error)
            raise ImportFailed(
                f"{where}: {why}: a shape has id, type, x, y, rotation and props (w and h, or points)"
            ) from None
        if points is None:
            raise ImportFailed(
                f"{where} (type {shape['type']!r}): neither props.w and props.h nor points to size "
                "it by: give it props.w and props.h, or remove it"
            )
        # A group's points are its children's bounds, on the page already.
        box = bounds(points) if shape["type"] == "group" else bounds(apply(matrix, p) for p in points)
        item.update(zip(("x0", "y0", "x1", "y1"), box, strict=True))
        return box


def _geometry(shape: dict, inside: list[tuple]) -> list[tuple[float, float]] | None:
    """The shape's outline points in its own frame (a group's: its children's page corners)."""
    kind, props = shape["type"], shape.get("props") or {}
    scale = float(props.get("scale", 1.0))
    if kind == "group":
        return [(b[i], b[j]) for b in inside for i, j in ((0, 1), (2, 3))] or None
    if "w" in props and "h" in props and kind != "text":
        return _rect(float(props["w"]), float(props["h"]) + float(props.get("growY") or 0.0))
    if kind == "note":
        return _rect(NOTE_SIZE * scale, (NOTE_SIZE + float(props.get("growY") or 0.0)) * scale)
    if kind == "text":
        lines = (_text(props) or " ").count("\n") + 1
        height = lines * FONT_SIZES.get(props.get("size", "m"), 24) * LINE_HEIGHT * scale
        return _rect(float(props.get("w", 0.0)) * scale, height)
    points: list[tuple[float, float]] = []
    if kind == "line" and props.get("points"):
        found = props["points"]
        points = [
            (float(p["x"]), float(p["y"])) for p in (found.values() if isinstance(found, dict) else found)
        ]
    elif kind in ("draw", "highlight") and props.get("segments"):
        points = [
            (float(p["x"]) * scale, float(p["y"]) * scale) for s in props["segments"] for p in s["points"]
        ]
    elif kind == "arrow":
        points = [
            (float(end.get("x", 0.0)), float(end.get("y", 0.0))) for end in (props["start"], props["end"])
        ]
    return points or None


def _text(props: dict) -> str:
    """A shape's text: ``props.text``, or the text nodes of ``props.richText`` (tldraw 3.x)."""
    if isinstance(props.get("text"), str):
        return props["text"]
    rich = props.get("richText")
    if not isinstance(rich, dict):
        return ""
    return "\n".join(_texts(block) for block in rich.get("content") or [])


def _texts(node: Any) -> str:
    """The text of a rich-text node and everything within it, in order; a loop, not recursion,
    so nodes nested however deep are no more than a long walk."""
    out, todo = [], [node]
    while todo:
        node = todo.pop()
        if isinstance(node, dict):
            out.append(str(node.get("text", "")))
            content = node.get("content")
            if isinstance(content, list):
                todo.extend(reversed(content))
    return "".join(out)


def _rect(w: float, h: float) -> list[tuple[float, float]]:
    return [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)]


def _local(x: float, y: float, angle: float) -> Matrix:
    c, s = math.cos(angle), math.sin(angle)
    return (c, s, -s, c, x, y)
