"""A document: its store rows plus an immutable in-memory snapshot that queries run on.

Queries read ``document.snapshot`` once and use only it, so an edit or import that swaps in
a new snapshot never shows a reader half of itself. Imports rebuild the snapshot from the
store; single-item edits copy the tree cheaply and overlay the changed items.
"""

from __future__ import annotations

import threading
from bisect import bisect_right
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from operator import itemgetter
from typing import Any

import numpy as np

from spatial import QuadTree

from .items import encode_item
from .store import Store

__all__ = ["Document", "Registry", "Snapshot"]

LOG_LIMIT = 100_000  # edits remembered for catching clients up; beyond, they start over


@dataclass(frozen=True)
class Snapshot:
    """One version of a document. Tree ids are positions into ``ids`` / ``encoded``."""

    version: int
    tree: QuadTree
    ids: list[str]  # shared between snapshots, never mutated
    encoded: "Packed"  # each item's response JSON, by position
    index: dict[str, int]  # id -> position for ids above, shared, never mutated
    overlay: dict[int, tuple[str, bytes]] = field(default_factory=dict)  # positions set by edits
    added: dict[str, int] = field(default_factory=dict)  # ids first created by edits
    # (version, item id) of every edit after version ``base``: shared and append-only, so a
    # snapshot reads only the entries up to its own version.
    log: list[tuple[int, str]] = field(default_factory=list)
    base: int = 0

    def item_id(self, pos: int) -> str:
        edit = self.overlay.get(pos)
        return edit[0] if edit else self.ids[pos]

    def item_json(self, pos: int) -> bytes:
        edit = self.overlay.get(pos)
        return edit[1] if edit else self.encoded[pos]

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

    def position(self, item_id: str) -> int | None:
        """The live position of ``item_id``, or None."""
        pos = self.added.get(item_id, self.index.get(item_id))
        return pos if pos is not None and pos in self.tree else None

    @property
    def next_position(self) -> int:
        return len(self.ids) + len(self.added)


class Document:
    def __init__(self, store: Store, meta: dict[str, Any]) -> None:
        self.store, self.id, self.name, self.created = store, meta["id"], meta["name"], meta["created"]
        self.snapshot = _load(store, self.id, meta["version"])
        self._edit_lock = threading.Lock()  # edits serialise; readers never wait
        self._watchers: set[Callable[[], None]] = set()

    def describe(self) -> dict[str, Any]:
        snap = self.snapshot
        return {"id": self.id, "name": self.name, "created": self.created, "version": snap.version,
                "items": len(snap.tree), "bounds": snap.tree.bounds}  # fmt: skip

    def watch(self, callback: Callable[[], None]) -> Callable[[], None]:
        """Call ``callback`` (from the editing thread) after each new version; returns the unwatch."""
        self._watchers.add(callback)
        return lambda: self._watchers.discard(callback)

    def import_items(self, items: Iterable[dict[str, Any]]) -> tuple[int, int]:
        """Store ``items`` all or nothing, then show them; ``(count, version)``.

        Holds the edit lock across both steps, so an edit can neither slip between the commit
        and the reload nor be overwritten by a snapshot carrying an older version number.
        """
        with self._edit_lock:
            count, version = self.store.import_items(self.id, items)
            self._publish(_load(self.store, self.id, version))
        return count, version

    def put(self, item: dict[str, Any]) -> tuple[int, bool]:
        """Store and show ``item``; ``(version, created)``."""
        with self._edit_lock:
            version = self.store.put_item(self.id, item)
            snap = self.snapshot
            tree = snap.tree.copy()
            box = (item["x0"], item["y0"], item["x1"], item["y1"])
            pos = snap.position(item["id"])
            created = pos is None
            added = snap.added
            if created:
                pos = snap.next_position
                tree.insert(pos, box)
                added = {**added, item["id"]: pos}
            else:
                tree.update(pos, box)
            encoded = encode_item(item["id"], box, item["kind"], item["z"], item["data"])
            overlay = {**snap.overlay, pos: (item["id"], encoded)}
            self._publish_edit(snap, item["id"], version, tree=tree, overlay=overlay, added=added)
            return version, created

    def delete(self, item_id: str) -> int:
        with self._edit_lock:
            snap = self.snapshot
            pos = snap.position(item_id)
            if pos is None:
                raise KeyError(item_id)
            version = self.store.delete_item(self.id, item_id)
            tree = snap.tree.copy()
            tree.remove(pos)
            self._publish_edit(snap, item_id, version, tree=tree)
            return version

    def _publish_edit(self, snap: Snapshot, item_id: str, version: int, **changes: Any) -> None:
        log, base = snap.log, snap.base
        if len(log) >= LOG_LIMIT:  # start over: clients further behind than this get a reset
            log, base = [], snap.version
        log.append((version, item_id))  # unseen by older snapshots: they read up to their version
        self._publish(replace(snap, version=version, log=log, base=base, **changes))

    def _publish(self, snap: Snapshot) -> None:
        self.snapshot = snap
        for callback in list(self._watchers):
            callback()


class Registry:
    """Every document of the store, loaded at start-up."""

    def __init__(self, store: Store) -> None:
        self.store = store
        self._docs = {meta["id"]: Document(store, meta) for meta in store.documents()}
        self._lock = threading.Lock()

    def __getitem__(self, doc_id: str) -> Document:
        try:
            return self._docs[doc_id]
        except KeyError:
            raise KeyError(f"document {doc_id!r} not found") from None

    def all(self) -> list[Document]:
        return list(self._docs.values())

    def create(self, name: str) -> Document:
        meta = self.store.create_document(name)
        doc = Document(self.store, meta)
        with self._lock:
            self._docs[doc.id] = doc
        return doc

    def delete(self, doc_id: str) -> None:
        self[doc_id]
        self.store.delete_document(doc_id)
        with self._lock:
            self._docs.pop(doc_id, None)


class Packed:
    """Many small byte strings in one buffer: a million separate bytes objects would cost
    their headers and, from orjson's oversized buffers, heap fragmentation."""

    def __init__(self, buffer: bytes, offsets: np.ndarray) -> None:
        self._buffer, self._offsets = buffer, offsets

    def __getitem__(self, pos: int) -> bytes:
        return self._buffer[self._offsets[pos] : self._offsets[pos + 1]]


def _load(store: Store, doc_id: str, version: int) -> Snapshot:
    ids: list[str] = []
    buffer = bytearray()
    offsets = [0]
    boxes = []
    for item_id, x0, y0, x1, y1, kind, z, data in store.items(doc_id):
        box = (x0, y0, x1, y1)
        ids.append(item_id)
        boxes.append(box)
        buffer += encode_item(item_id, box, kind, z, data)
        offsets.append(len(buffer))
    tree = QuadTree.bulk_load(np.array(boxes, dtype=np.float64).reshape(-1, 4))
    encoded = Packed(bytes(buffer), np.array(offsets, dtype=np.int64))
    index = {item_id: pos for pos, item_id in enumerate(ids)}
    return Snapshot(version, tree, ids, encoded, index, base=version)
