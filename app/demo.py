"""Demo documents worth panning: a 2000-page report and a clustered whiteboard (~1.3M items)."""

from collections.abc import Iterator
from pathlib import Path

import msgspec
import numpy as np
import orjson
from tqdm import tqdm

from spatial import scenes

from .items import Item, batch_of
from .stores import Store
from .table import ItemTable

__all__ = ["DEMOS", "create_demos", "ndjson_lines"]

DEMOS = {
    "Demo: 2000-page report": lambda: scenes.long_document(pages=2000, seed=1),
    "Demo: whiteboard": lambda: scenes.whiteboard(n=300_000, seed=2, clusters=120),
}


def create_demos(store: Store, snapshots: Path) -> list[str]:
    """Create the demo documents missing from ``store``, with their snapshot files (so a
    server's first request maps them); returns the names created."""
    from .registry import Registry
    from .snapfile import SnapshotFiles

    present = {doc["name"] for doc in store.documents()}
    registry = Registry(store, SnapshotFiles(snapshots), budget=0)
    created = []
    for name, make in tqdm([(n, m) for n, m in DEMOS.items() if n not in present], desc="demo documents"):
        boxes, kinds = make()
        batch = batch_of(list(_items(boxes, kinds)), max_data_bytes=4096)
        document = registry.create(name)
        document.import_table(ItemTable.merge([ItemTable.of(batch.ids, batch.boxes, batch.bodies)]))
        registry.evict()
        created.append(name)
    return created


# Words for the demo's text boxes (seeded): common ones often, the rarer ones now and then,
# so a search finds a few hits or many.
_PARAGRAPH = (
    "the of and to in a is that for it as was with be by on not he this are or his from at which "
    "but have an they you were her she there been one all we their has would when if will more no "
    "out so up said what its about than into them can only other new some could time these two may "
    "first then do any like my now over such our man me even most made after also did many before "
    "must through years where much your way well down should because each just those people how too "
    "quarterly revenue forecast margin ledger audit vantage canvas quadtree viewport whiteboard report"
)
WORDS = _PARAGRAPH.split()
RARE = 24  # the last words are rarer


def _items(boxes: np.ndarray, kinds: np.ndarray) -> Iterator[Item]:
    names = scenes.KINDS
    rng = np.random.default_rng(7)
    weights = np.r_[np.full(len(WORDS) - RARE, 40.0), np.ones(RARE)]
    words = rng.choice(len(WORDS), size=len(boxes), p=weights / weights.sum()).tolist()
    for i, ((x0, y0, x1, y1), kind) in enumerate(zip(boxes.tolist(), kinds.tolist(), strict=True)):
        z = 0 if kind in (scenes.PAGE, scenes.FRAME) else 1
        data = {"text": WORDS[words[i]]} if kind == scenes.TEXT else msgspec.UNSET
        yield Item(f"{names[kind][0]}{i}", x0, y0, x1, y1, names[kind], z, data)


_CHUNK = 1 << 16  # rows made Python objects at a time


def ndjson_lines(boxes: np.ndarray, kinds: np.ndarray | None = None) -> Iterator[bytes]:
    """A generated scene as import lines: ids ``i0``, ``i1``..., kind names, ``z = i % 7``;
    floats keep all their digits. Made a chunk of rows at a time: 100M boxes as Python floats
    at once would take ~15 GB."""
    names = scenes.KINDS
    for start in range(0, len(boxes), _CHUNK):
        rows = boxes[start : start + _CHUNK].tolist()
        kind_list = kinds[start : start + _CHUNK].tolist() if kinds is not None else None
        for i, (x0, y0, x1, y1) in enumerate(rows, start):
            item = {"id": f"i{i}", "x0": x0, "y0": y0, "x1": x1, "y1": y1, "z": i % 7}
            if kind_list is not None:
                item["kind"] = names[kind_list[i - start]]
            yield orjson.dumps(item) + b"\n"
