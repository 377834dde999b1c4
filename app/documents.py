"""A document: its store rows plus an immutable in-memory snapshot that queries run on.

Queries read ``document.snapshot`` once and use only it, so an edit or import that swaps in
a new snapshot never shows a reader half of itself. An import builds a new snapshot from the
merged item table it stores; single-item edits copy the tree cheaply and overlay the changed
items.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from bisect import bisect_right
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from operator import itemgetter
from typing import Any

import msgspec
import numpy as np
from fastapi.concurrency import run_in_threadpool

from spatial import QuadTree
from spatial.overview import Overview

from .errors import Conflict, NotFound, TooMany
from .housekeeping import return_freed_memory
from .items import Batch
from .looks import Looks, agg_id, agg_json, band_json
from .store import Store
from .table import ItemTable, Packed

__all__ = ["Document", "Registry", "Snapshot", "pack"]

log = logging.getLogger("vantage.import")
LOG_LIMIT = 100_000  # edits remembered for catching clients up; beyond, they start over


@dataclass(frozen=True)
class Snapshot:
    """One version of a document. Tree ids are positions into ``table``, then into edits."""

    version: int
    tree: QuadTree
    table: ItemTable  # the items as loaded or imported; shared between snapshots, never mutated
    overlay: dict[int, tuple[bytes, bytes]] = field(default_factory=dict)  # pos -> (JSON id, body) by edits
    added: dict[str, int] = field(default_factory=dict)  # ids first created by edits
    # (version, item id) of every edit after version ``base``: shared and append-only, so a
    # snapshot reads only the entries up to its own version.
    log: list[tuple[int, str]] = field(default_factory=list)
    base: int = 0
    next_position: int = -1  # where an edit puts the next new item; never reused
    # What stands in for items too small to draw, per zoom band, and the kinds and z it was built from
    overview: Overview | None = None
    looks: Looks | None = None
    # Each band's aggregates as built, as JSON, made on first use; shared by the snapshots of
    # one build (edits change a few aggregates, which are encoded apart)
    agg_bodies: dict[int, Packed] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.next_position < 0:
            object.__setattr__(self, "next_position", len(self.table))

    def item_id(self, pos: int) -> str:
        edit = self.overlay.get(pos)
        return msgspec.json.decode(edit[0]) if edit else self.table.item_id(pos)

    def item_json(self, pos: int) -> bytes:
        edit = self.overlay.get(pos)
        return edit[1] if edit else self.table.bodies[pos]

    def items_array(self, positions: np.ndarray) -> bytes:
        """The JSON array of the items at ``positions``."""
        return self._array(positions, self.table.bodies, 1)

    def entries_array(self, positions: np.ndarray, band: int | None, aggregates: np.ndarray) -> bytes:
        """The JSON array of the items at ``positions`` and of ``band``'s ``aggregates``."""
        if band is None or not len(aggregates):
            return self._array(positions, self.table.bodies, 1)
        overview, names = self.overview, self.looks.names  # type: ignore[union-attr]
        bodies = self.agg_bodies.get(band)
        if bodies is None:
            bodies = self.agg_bodies[band] = band_json(overview, names, band)  # type: ignore[arg-type]
        edited = np.isin(aggregates, overview.edited(band)) | (aggregates >= len(bodies))  # type: ignore[union-attr]
        more = agg_json(overview, names, band, aggregates[edited]) if edited.any() else []  # type: ignore[arg-type]
        built = aggregates[~edited]
        if len(built):
            more.append(bodies.join(built))
        return self._array(positions, self.table.bodies, 1, more)

    def ids_array(self, positions: np.ndarray, more: Sequence[bytes] = ()) -> bytes:
        """The JSON array of the ids at ``positions``, then of the JSON strings ``more``."""
        return self._array(positions, self.table.ids, 0, more)

    def _array(self, positions: np.ndarray, packed: Packed, field: int, more: Sequence[bytes] = ()) -> bytes:
        if self.overlay:  # edited items come from the overlay, the rest from the table
            edited = np.isin(positions, self._edited_positions)
            more = [*more, *(self.overlay[p][field] for p in positions[edited].tolist())]
            positions = positions[~edited]
        parts = [packed.join(positions)] if len(positions) else []
        return b"[" + b",".join(parts + list(more)) + b"]"

    @cached_property
    def _edited_positions(self) -> np.ndarray:
        return np.fromiter(self.overlay, np.int64, len(self.overlay))

    def position(self, item_id: str) -> int | None:
        """The live position of ``item_id``, or None."""
        pos = self.added.get(item_id)
        if pos is None:
            pos = self.table.position(item_id)
        return pos if pos is not None and pos in self.tree else None

    def stored_table(self) -> ItemTable | None:
        """The table, when it is all the store holds (no edit since the import that built it):
        an import then merges with it instead of reading a second copy from the store."""
        return self.table if not self.overlay and len(self.tree) == len(self.table) else None

    def edited_since(self, version: int) -> list[str] | None:
        """Ids edited after ``version`` up to this snapshot; None when the log does not reach
        back that far (an import since, or an old version), so the caller must start over.

        :raises ValueError: if ``version`` is newer than this snapshot
        """
        if version > self.version:
            raise ValueError(f"version {version} is newer than the document's version {self.version}")
        if version < self.base:
            return None
        start = bisect_right(self.log, version, key=itemgetter(0))
        end = bisect_right(self.log, self.version, key=itemgetter(0))
        return list(dict.fromkeys(item_id for _, item_id in self.log[start:end]))


class Document:
    def __init__(self, store: Store, meta: dict[str, Any]) -> None:
        self.store, self.id, self.name, self.created = store, meta["id"], meta["name"], meta["created"]
        self.snapshot = _snapshot(store.read_items(self.id), meta["version"])
        self._edit_lock = threading.Lock()  # edits serialise; readers never wait
        self._writing = asyncio.Lock()  # the same, for writers that wait on the event loop
        self._watchers: set[Callable[[], None]] = set()
        self.deleted = False

    def describe(self) -> dict[str, Any]:
        snap = self.snapshot
        return {
            "id": self.id,
            "name": self.name,
            "created": self.created,
            "version": snap.version,
            "items": len(snap.tree),
            "bounds": snap.tree.bounds,
        }

    async def write(self, edit: Callable[..., Any], *args: Any) -> Any:
        """``edit(*args)`` in a worker thread once the document's earlier writes are done.
        Writers queue here, on the event loop, so a long import never lets them fill the
        thread pool that every other document's requests need."""
        async with self._writing:
            return await run_in_threadpool(edit, *args)

    def watch(self, callback: Callable[[], None]) -> Callable[[], None]:
        """Call ``callback`` (from the editing thread) after each new version; returns the unwatch."""
        self._watchers.add(callback)
        return lambda: self._watchers.discard(callback)

    def import_items(self, batches: Iterable[Batch], max_items: int | None = None) -> tuple[int, int]:
        """Store the items of ``batches`` all or nothing (upsert by id), then show them;
        ``(distinct items imported, version)``. If iterating ``batches`` raises, nothing changes."""
        return self.import_table(pack(batches), max_items)

    def import_table(self, imported: ItemTable, max_items: int | None = None) -> tuple[int, int]:
        """Store ``imported`` (from ``pack``) all or nothing, upserting by id, then show it.

        Holds the edit lock throughout, so an edit can neither slip between the commit and
        the new snapshot nor be overwritten by a snapshot carrying an older version number.

        :raises TooMany: if the document would hold more than ``max_items``
        """
        with self._edit_lock:
            current = (
                [self.snapshot.stored_table() or self.store.read_items(self.id)]
                if len(self.snapshot.tree)
                else []
            )
            table = ItemTable.merge([*current, imported])
            if max_items is not None and len(table) > max_items:
                raise TooMany(
                    f"the document would hold {len(table)} items; the most is {max_items} (VANTAGE_MAX_ITEMS)"
                )
            log.info("import into %s: storing %d items", self.id, len(table))
            version = self.store.write_items(self.id, table)
            self._publish(_snapshot(table, version))
        count = len(imported)
        del current, table, imported
        return_freed_memory()
        return count, version

    def put(self, item: Batch, max_items: int | None = None) -> tuple[int, bool]:
        """Store and show one item (a batch of one); ``(version, created)``.

        :raises TooMany: if it is new and the document already holds ``max_items``
        """
        (item_id,), (body,) = item.ids, item.bodies
        box = tuple(item.boxes[0].tolist())
        with self._edit_lock:
            snap = self.snapshot
            pos = snap.position(item_id)
            created = pos is None
            if max_items is not None and created and len(snap.tree) >= max_items:
                raise TooMany(
                    f"the document holds {len(snap.tree)} items, the most it may (VANTAGE_MAX_ITEMS)"
                )
            version = self.store.put_item(self.id, item_id, box, body)
            tree = snap.tree.copy()
            overview, looks = snap.overview.copy(), snap.looks.with_item(body)  # type: ignore[union-attr]
            added = snap.added
            if created:
                pos = snap.next_position
                tree.insert(pos, box)
                added = {**added, item_id: pos}
                changed = set()
            else:
                changed = overview.remove(pos, tree.get(pos))
                tree.update(pos, box)
            changed |= overview.insert(pos, box, *looks.of_body(body))
            overlay = {**snap.overlay, pos: (msgspec.json.encode(item_id), body)}
            self._publish_edit(
                snap,
                [item_id, *map(agg_id, sorted(changed))],
                version,
                tree=tree,
                overlay=overlay,
                added=added,
                next_position=max(snap.next_position, pos + 1),
                overview=overview,
                looks=looks,
            )
            return version, created

    def delete(self, item_id: str) -> int:
        with self._edit_lock:
            snap = self.snapshot
            pos = snap.position(item_id)
            if pos is None:
                raise NotFound(f"item {item_id!r} not found in document {self.id!r}")
            version = self.store.delete_item(self.id, item_id)
            tree = snap.tree.copy()
            overview = snap.overview.copy()  # type: ignore[union-attr]
            changed = overview.remove(pos, tree.get(pos))
            tree.remove(pos)
            self._publish_edit(
                snap, [item_id, *map(agg_id, sorted(changed))], version, tree=tree, overview=overview
            )
            return version

    def _publish_edit(self, snap: Snapshot, ids: list[str], version: int, **changes: Any) -> None:
        """Publish an edit that changed ``ids`` (the item's, then the aggregates' it changed)."""
        log, base = snap.log, snap.base
        if len(log) >= LOG_LIMIT:  # start over: clients further behind than this get a reset
            log, base = [], snap.version
        log.extend((version, i) for i in ids)  # unseen by older snapshots: they read up to their version
        self._publish(replace(snap, version=version, log=log, base=base, **changes))

    def _publish(self, snap: Snapshot) -> None:
        self.snapshot = snap
        for callback in list(self._watchers):
            callback()


class Registry:
    """Every document of the store, loaded at start-up."""

    def __init__(self, store: Store, max_documents: int | None = None) -> None:
        self.store, self.max_documents = store, max_documents
        self._docs = {meta["id"]: Document(store, meta) for meta in store.documents()}
        return_freed_memory()
        self._lock = threading.Lock()

    def __getitem__(self, doc_id: str) -> Document:
        try:
            return self._docs[doc_id]
        except KeyError:
            raise NotFound(f"document {doc_id!r} not found") from None

    def all(self) -> list[Document]:
        return list(self._docs.values())

    def create(self, name: str) -> Document:
        """:raises Conflict: if the store holds ``max_documents`` already"""
        with self._lock:
            if self.max_documents is not None and len(self._docs) >= self.max_documents:
                raise Conflict(
                    f"the store holds {len(self._docs)} documents, the most it may "
                    "(VANTAGE_MAX_DOCUMENTS): delete one first"
                )
            doc = Document(self.store, self.store.create_document(name))
            self._docs[doc.id] = doc
        return doc

    def delete(self, doc_id: str) -> None:
        """Delete the document; its open streams are told (``Document.deleted``)."""
        doc = self[doc_id]
        with doc._edit_lock:
            self.store.delete_document(doc_id)
            with self._lock:
                self._docs.pop(doc_id, None)
            doc.deleted = True
            doc._publish(doc.snapshot)


def pack(batches: Iterable[Batch]) -> ItemTable:
    """The items of ``batches`` as one table, a repeated id keeping its last box (an upsert).
    Packed a batch at a time: a million Python strings at once would linger as heap.

    :raises: whatever iterating ``batches`` raises (a bad line, say)
    """
    return ItemTable.merge([ItemTable.of(b.ids, b.boxes, b.bodies) for b in batches] or [ItemTable.empty()])


def _snapshot(table: ItemTable, version: int) -> Snapshot:
    looks, kinds, z = Looks.of(table.bodies)
    overview = Overview.build(table.boxes, kinds, z)
    return Snapshot(
        version, QuadTree.bulk_load(table.boxes), table, base=version, overview=overview, looks=looks
    )
