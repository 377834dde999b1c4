"""Excalidraw scenes (``.excalidraw``: ``{"type": "excalidraw", "elements": [...]}``; the
clipboard's ``excalidraw/clipboard`` too). Each element not deleted becomes an item: its id,
``kind`` its type, ``z`` its place in the array (later ones are drawn on top), its box the
axis-aligned bounds of the element turned by its ``angle`` about its centre. Lines, arrows and
freehand strokes are bounded by their points (relative to ``x``, ``y``), turned the same way;
text keeps its text in ``data``."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .base import ImportFailed, Source, bounds, json_of, rotated

__all__ = ["NAME", "SUFFIXES", "detect", "read"]

NAME = "Excalidraw"
SUFFIXES = (".excalidraw",)
TYPES = ("excalidraw", "excalidraw/clipboard")
POINTED = ("line", "arrow", "freedraw")


def detect(path: Path, head: bytes) -> bool:
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    return path.suffix.lower() in SUFFIXES or (
        text.startswith(b"{") and any(b'"type":"%s"' % t.encode() in text.replace(b" ", b"") for t in TYPES)
    )


def read(source: Source) -> Iterator[tuple[str, dict]]:
    scene = json_of(source, "export the scene again from Excalidraw")
    if (
        not isinstance(scene, dict)
        or scene.get("type") not in TYPES
        or not isinstance(scene.get("elements"), list)
    ):
        raise ImportFailed(
            'not an Excalidraw scene: one is {"type": "excalidraw", "elements": [...]}; save it '
            "with Excalidraw's Save to… / Export"
        )
    elements = scene["elements"]
    for n, element in enumerate(elements):
        if not isinstance(element, dict) or element.get("isDeleted"):
            continue
        where = f"element {n} (id {element.get('id')!r})"
        try:
            yield where, _item(element, n)
        except (KeyError, TypeError, ValueError) as error:
            raise ImportFailed(
                f"{where}: {_why(error)}: an element has id, type, x, y, width, height (and angle, points)"
            ) from None
        source.done = source.size * (n + 1) // len(elements)


def _item(element: dict[str, Any], z: int) -> dict[str, Any]:
    x, y, angle = float(element["x"]), float(element["y"]), float(element.get("angle") or 0.0)
    points = element.get("points")
    if element["type"] in POINTED and points:
        corners = [(x + float(px), y + float(py)) for px, py, *_ in points]
    else:
        w, h = float(element["width"]), float(element["height"])
        corners = [(x, y), (x + w, y), (x + w, y + h), (x, y + h)]
    x0, y0, x1, y1 = bounds(corners)
    x0, y0, x1, y1 = bounds(rotated(corners, angle, (x0 + x1) / 2, (y0 + y1) / 2))
    item = {"id": element["id"], "x0": x0, "y0": y0, "x1": x1, "y1": y1, "kind": element["type"], "z": z}
    if isinstance(element.get("text"), str) and element["text"]:
        item["data"] = {"text": element["text"]}
    elif element["type"] == "frame" and element.get("name"):
        item["data"] = {"name": element["name"]}
    return item


def _why(error: Exception) -> str:
    if isinstance(error, KeyError):
        return f"no {error.args[0]!r}"
    return str(error)
