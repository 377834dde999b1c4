"""A document's base in a snapshot file: its index and items, mapped, not rebuilt (the file's
format: ``snapformat``).

``save`` writes a base built in memory; ``write_base`` builds one straight into its file, a
part at a time, never holding it whole (an import's, a compaction's), its runs held to a
``MemoryBudget``: ``import_budget``, the import's memory policy, sizes it to what
``VANTAGE_IMPORT_MEMORY_MB`` leaves. ``load`` maps a file back as a ``Snapshot`` whose blocks
are checked as they are first read.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Mapping
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from spatial import MemoryBudget, QuadTree
from spatial.budget import LEAST_RUN_BYTES
from spatial.kernels import index_type
from spatial.overview import Overview
from spatial.paging import in_steps, mapping, release

from .blocks import SnapshotCorrupt
from .frames import DecodedFrames, Framed, framed_arrays, places_in, taken
from .heap import return_freed_memory
from .looks import Looks
from .packed import Packed, scratch_array, spilled_arrays
from .snapformat import SnapshotFileError, Writer, read
from .snapshots import Snapshot
from .table import ItemTable, high_halves
from .text import TextIndex

__all__ = ["IMPORT_BYTES", "RUNTIME_BYTES", "import_budget", "load", "save", "write_base"]

log = logging.getLogger("vantage.import")

# What an import's build aims to hold at its peak (``VANTAGE_IMPORT_MEMORY_MB``): its runs are
# sized to what is left of it once the process's runtime (the interpreter, numpy, numba's
# compiled code: ~240 MB measured) and what the build holds whole (the tree's nodes and their
# ranges, a band's rows: ~5-7 bytes an item at 1e8 items) are counted
IMPORT_BYTES = 1400 << 20
RUNTIME_BYTES = 256 << 20
WHOLE_BYTES_PER_ITEM = 7


def import_budget(items: int, import_bytes: int = IMPORT_BYTES) -> MemoryBudget:
    """The budget of a build of ``items`` (an import's, a compaction's) that aims to hold at
    most ``import_bytes`` at its peak: runs of half of what is left of it, between
    ``LEAST_RUN_BYTES`` and ``MOST_RUN_BYTES`` (``MemoryBudget.of_runs``). Past what the
    document needs at the least, it still imports, with runs at their least (logged)."""
    left = (import_bytes - RUNTIME_BYTES - WHOLE_BYTES_PER_ITEM * items) // 2
    if left < LEAST_RUN_BYTES:
        least = RUNTIME_BYTES + WHOLE_BYTES_PER_ITEM * items + 2 * LEAST_RUN_BYTES
        log.warning(
            "an import of %d items holds ~%d MB at the least, past the %d MB it aims at "
            "(VANTAGE_IMPORT_MEMORY_MB): its runs are at their least",
            items,
            least >> 20,
            import_bytes >> 20,
        )
    return MemoryBudget.of_runs(left)


def save(snap: Snapshot, path: Path) -> int:
    """Write ``snap``'s base (no edits), built in memory, to ``path`` as a snapshot file; its size."""
    assert not snap.edits and snap.base_id is not None, "only a fresh base is saved"
    assert snap.looks is not None and snap.overview is not None and snap.text is not None, "a built base"
    meta = {"version": snap.version, "base_id": snap.base_id, "kinds": list(snap.looks.names)}
    tree, text, overview = snap.tree, snap.text, snap.overview
    return _write(
        path,
        meta,
        snap.table,
        lambda: iter(overview.to_arrays().items()),
        partial(_tree_arrays, tree, snap.table),
        lambda: text,
    )


def _tree_arrays(
    tree: QuadTree, table: ItemTable, put: Callable[[np.ndarray], object]
) -> dict[str, np.ndarray]:
    """``tree``'s arrays, its boxes handed to ``put`` (a float32 tree's: the items' own, exact,
    in its order; its own among the arrays returned)."""
    parts = tree.to_arrays()
    boxes = parts.pop("boxes")
    if boxes.dtype == np.float64:
        put(boxes)
    else:
        put(table.read_boxes()[parts["ids"]])
        parts["boxes"] = boxes
    return parts


def write_base(
    table: ItemTable, path: Path, version: int, base_id: str, budget: MemoryBudget | None = None
) -> int:
    """Build the base of ``table`` at ``version`` straight into a snapshot file at ``path``
    (``build`` builds one in memory): each part (the overview, the tree, the text) is built,
    written, and let go before the next, so the whole base is never held at once; their
    runs held to ``budget`` (None: ``import_budget`` of the default aim). The file's size."""
    with (budget or import_budget(len(table))).held():
        return _write_base(table, path, version, base_id)


def _write_base(table: ItemTable, path: Path, version: int, base_id: str) -> int:
    bodies = table.bodies.unpacked()
    # Each item's kind and z, for the overview: in files (a column of one value aside), read
    # a step at a time, 4 bytes an item each less through the scan and the overview's build
    looks, *columns = Looks.of(bodies, partial(scratch_array, path.parent))
    bodies.release()  # read through: a spilled import's bodies go back to the page cache
    return_freed_memory()  # the scan's heap (~14 bytes an item that glibc would keep)
    meta = {"version": version, "base_id": base_id, "kinds": list(looks.names)}

    def overview() -> Iterator[tuple[str, np.ndarray]]:
        kinds, z = columns
        columns.clear()  # let go once it is built
        homes = scratch_array(path.parent, len(table), np.int32)  # in a file as they are made
        # ... and the band below while the next is merged
        return Overview.build_arrays(
            table.boxes, kinds, z, homes=homes, scratch=partial(scratch_array, path.parent)
        )

    def text() -> TextIndex:
        bodies = table.bodies.unpacked()
        try:
            return TextIndex.of_table(bodies)
        finally:
            bodies.release()

    tree = partial(QuadTree.build_arrays, table.boxes, scratch=partial(scratch_array, path.parent))
    return _write(path, meta, table, overview, tree, text)


def _write(
    path: Path,
    meta: Mapping[str, Any],
    table: ItemTable,
    overview: Callable[[], Iterator[tuple[str, np.ndarray]]],
    tree: Callable[[Callable[[np.ndarray], object]], dict[str, np.ndarray]],
    text: Callable[[], TextIndex],
) -> int:
    """Write the base of ``table`` whose parts ``overview`` and ``tree`` (their arrays) and
    ``text`` make, in that order (the overview's build peaks highest: it comes while the least
    is held), to ``path``; its size.

    Its items are laid out in the tree's order: a screen's items lie in a few runs of the file,
    not one a block. The table (with its id index, and ``rank``: each position's place in the
    document's order), the tree (its ids are then its slots 0..n-1, stored nowhere), the
    overview and the text, their positions moved with the items. The table's boxes are the
    tree's own array, written once; its bodies are compressed a frame at a time (``frames``)
    straight into the file. The answers do not change: they follow the tree's order, the
    overview's aggregates and the text's order are built before the items move, and ``rank``
    keeps the document's order.
    """
    with Writer(path) as out:
        homes = np.empty(0, np.int32)
        for name, array in overview():  # each band written as it is made (``build_arrays``)
            if name == "homes":  # moved with the items once the tree has placed them: in a
                # file till then (an import's are made there), not held
                homes = array if mapping(array) is not None else spilled_arrays([array], path.parent)[0]
            else:
                out.add(f"overview.{name}", array)
        del array  # let go once written, as each part is before the next is built
        return_freed_memory()
        # The items' boxes, in the tree's order, written as its build makes them
        with out.appending("boxes", np.dtype(np.float64).str, 4) as boxes:
            parts = tree(boxes.add)
        rank = parts.pop("ids")  # a fresh base's tree holds each position once: where each went
        n = len(rank)
        assert n == len(table), "a fresh base: its tree holds the whole table"
        if "boxes" not in parts:  # the tree's boxes are the items': written once
            out.same("tree.boxes", "boxes")
        shape = np.append(parts.pop("shape"), 1)  # its ids are its slots: stored nowhere
        _add(out, {**{f"tree.{k}": v for k, v in parts.items()}, "tree.shape": shape})
        del parts, shape
        rank = rank.astype(index_type(n), copy=False)
        out.add("rank", rank)
        # ... then kept in a file, as where each position went (``slot``): each read a step
        # at a time from here, or at random with its pages handed back after (``_taken``)
        rank = rank if mapping(rank) is not None else spilled_arrays([rank], path.parent)[0]
        slot = places_in(rank, n, path.parent)
        # Each array below made and written a step at a time, what it reads handed back
        _add_made(out, "overview.homes", rank, partial(_taken, homes))
        del homes
        ids = taken(table.ids, rank, path.parent, slot)  # into a file a step at a time, not held
        out.add("ids.buffer", ids.array)
        width = index_type(len(ids.array))  # int32 while they fit
        _add_made(out, "ids.offsets", ids.offsets, lambda step: step.astype(width))
        del ids
        hashes, order = table._index
        _add_made(out, "index.hashes", hashes, high_halves)
        _add_made(out, "index.order", order, partial(_taken, slot))
        del hashes, order
        table.release()  # a spilled table's pages read so far (``ItemTable.spilled``)
        with out.appending("bodies.frames") as frames:
            framing = framed_arrays(table.bodies.unpacked(), rank, path.parent, frames, places=slot)
        table.release()
        _add(out, {f"bodies.{k}": v for k, v in framing.items()})
        del framing
        parts = text().to_arrays()
        parts["positions"] = _taken(slot, parts["positions"]).astype(np.int64)
        _add(out, {f"text.{k}": v for k, v in parts.items()})
        del parts
        return out.finish(meta)


def load(path: Path, base_id: str, version: int, decoded: DecodedFrames | None = None) -> Snapshot:
    """The snapshot saved at ``path``, mapped, if it is the base ``base_id`` at ``version``;
    its blocks are checked as they are first read, its items' frames decoded into ``decoded``
    (None: a cache of its own).

    :raises SnapshotFileError: if the file is missing, its header corrupt, or of another base
    """
    meta, arrays, size, blocks = read(path)
    if meta.get("base_id") != base_id or meta.get("version") != version:
        raise SnapshotFileError(
            f"{path}: of base {meta.get('base_id')} at version {meta.get('version')}, not {base_id} at {version}"
        )
    try:  # the few numbers an open reads: the trees' shapes, the overview's bands
        blocks.check(
            *(a for name, a in arrays.items() if name.endswith("shape") or name == "overview.levels")
        )
    except SnapshotCorrupt:
        raise SnapshotFileError(str(blocks.bad)) from None
    try:
        table = ItemTable(
            Packed(arrays["ids.buffer"].data, arrays["ids.offsets"], blocks),  # memoryviews of the map
            Framed(
                arrays["bodies.frames"],
                arrays["bodies.at"],
                arrays["bodies.first"],
                arrays["bodies.offsets"],
                blocks,
                decoded,
            ),
            arrays["boxes"],
            blocks,
        )
        table.__dict__["_index"] = (
            arrays["index.hashes"],
            arrays["index.order"],
        )  # the cached_property's slot
        tree = QuadTree.from_arrays(_under(arrays, "tree."), blocks)
        overview = Overview.from_arrays(_under(arrays, "overview."), blocks)
        text = TextIndex.from_arrays(_under(arrays, "text."))
        rank = arrays["rank"]
    except (KeyError, ValueError) as error:
        raise SnapshotFileError(f"{path}: not a snapshot ({error})") from None
    names = tuple(meta["kinds"])
    looks = Looks(names, {n: k for k, n in enumerate(names)})
    return Snapshot.base_of(table, tree, overview, looks, text, version, base_id, size, blocks, rank)


def _under(arrays: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
    return {k[len(prefix) :]: v for k, v in arrays.items() if k.startswith(prefix)}


def _add(out: Writer, arrays: Mapping[str, np.ndarray]) -> None:
    """Write each of ``arrays``: one given under two names (the same object) once."""
    first: dict[int, str] = {}  # the arrays are all held meanwhile: no id is reused
    for name, array in arrays.items():
        if (written := first.setdefault(id(array), name)) != name:
            out.same(name, written)
        else:
            out.add(name, array)


def _add_made(out: Writer, name: str, rows: np.ndarray, make: Callable[[np.ndarray], np.ndarray]) -> None:
    """Write ``make(rows)`` (one value a row) as ``name``, made a step of ``rows`` at a time
    (their pages handed back after each, mapped from a file): never held whole."""
    with out.appending(name, make(rows[:0]).dtype.str) as appended:
        for _, step in in_steps(rows):
            appended.add(make(step))


def _taken(column: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``column[rows]``, the pages of ``column`` read at random handed back (mapped)."""
    taken = column[rows]
    release(column)
    return taken
