"""The scenes every trade but overscan runs on: boxes, kinds, a panning path, a default tree."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from spatial import Rect, scenes
from spatial.quadtree import QuadTree

SCENE_KEYS = ("doc", "whiteboard", "clustered", "uniform")


@dataclass
class Scene:
    key: str
    title: str
    boxes: np.ndarray  # (n, 4) float64
    kinds: np.ndarray  # (n,) uint8 into scenes.KINDS
    cols: tuple[np.ndarray, ...]  # contiguous x0, y0, x1, y1: brute force streams them
    views: list[Rect]  # the panning path
    tree: QuadTree  # default options


def load_scene(key: str, scale: float, seed: int, steps: int) -> Scene:
    if key == "doc":
        pages = max(1, round(2000 * scale))
        boxes, kinds = scenes.long_document(pages=pages, seed=seed)
        title = f"long document ({pages:,} pages)"
    elif key == "clustered":
        n = max(1000, round(200_000 * scale))
        boxes, kinds = scenes.clustered_board(n=n, seed=seed)
        title = f"clustered board ({n:,} notes)"
    else:
        n = max(1000, round(1_000_000 * scale))
        maker = scenes.whiteboard if key == "whiteboard" else scenes.uniform
        boxes, kinds = maker(n=n, seed=seed)
        title = key
    views = [as_rect(r) for r in scenes.panning_path(boxes, steps, seed)]
    return Scene(key, title, boxes, kinds, columns(boxes), views, QuadTree.bulk_load(boxes))


def columns(boxes: np.ndarray) -> tuple[np.ndarray, ...]:
    return tuple(np.ascontiguousarray(boxes[:, i]) for i in range(4))


def as_rect(r: Sequence[float]) -> Rect:
    return float(r[0]), float(r[1]), float(r[2]), float(r[3])
