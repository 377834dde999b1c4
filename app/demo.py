"""Demo documents worth panning: a 2000-page report and a clustered whiteboard (~1.3M items)."""

from collections.abc import Iterator
from typing import Any

import numpy as np
from tqdm import tqdm

from spatial import scenes

from .store import Store

__all__ = ["DEMOS", "create_demos"]

DEMOS = {
    "Demo: 2000-page report": lambda: scenes.long_document(pages=2000, seed=1),
    "Demo: whiteboard": lambda: scenes.whiteboard(n=300_000, seed=2, clusters=120),
}


def create_demos(store: Store) -> list[str]:
    """Create the demo documents missing from ``store``; returns the names created."""
    present = {doc["name"] for doc in store.documents()}
    created = []
    for name, make in DEMOS.items():
        if name in present:
            continue
        boxes, kinds = make()
        doc = store.create_document(name)
        rows = tqdm(_items(boxes, kinds), total=len(boxes), desc=name, unit=" items", unit_scale=True)
        store.import_items(doc["id"], rows)
        created.append(name)
    return created


def _items(boxes: np.ndarray, kinds: np.ndarray) -> Iterator[dict[str, Any]]:
    names = scenes.KINDS
    for i, ((x0, y0, x1, y1), kind) in enumerate(zip(boxes.tolist(), kinds.tolist(), strict=True)):
        yield {"id": f"{names[kind][0]}{i}", "x0": x0, "y0": y0, "x1": x1, "y1": y1,
               "kind": names[kind], "z": 0 if kind in (scenes.PAGE, scenes.FRAME) else 1, "data": None}  # fmt: skip
