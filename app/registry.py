"""The registry: a store's documents, opened on demand within a memory budget, and kept up to
date with what any process writes to the store.

A document stays open while it is used (a request, a stream); the least recently used ones
close when the open ones hold more than the budget. Other processes' writes reach the open
documents through the store's change log, looked at once per turn of the event loop.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
import weakref
from collections import OrderedDict
from functools import partial
from typing import Any

from fastapi.concurrency import run_in_threadpool

from .documents import Document
from .errors import Behind, Conflict, NotFound
from .snapfile import SnapshotFiles
from .stores import Store, StoreUnavailable

__all__ = ["Registry"]

log = logging.getLogger("vantage.import")
REACH_POLL_SECONDS = 0.02  # how often a request waiting for a version looks again


class Registry:
    """The store's documents, opened on demand: those used most recently stay open while the
    open ones hold at most ``budget`` bytes; one in use (a request, a stream) never closes."""

    def __init__(
        self,
        store: Store,
        files: SnapshotFiles,
        budget: int,
        max_documents: int | None = None,
        tile_bytes: int = 128 << 20,
    ) -> None:
        self.store, self.files, self.budget, self.max_documents = store, files, budget, max_documents
        self.tile_bytes = tile_bytes  # most bytes of tiles each open document keeps (in budget)
        self._open: OrderedDict[str, Document] = OrderedDict()
        self._lock = threading.Lock()  # guards _open and the counts
        self._opening: dict[str, threading.Lock] = {}  # one opener per document
        self._looking = asyncio.Lock()  # one read of the change log at a time
        self._catching_up: dict[str, asyncio.Task] = {}  # documents being caught up, and by what
        self._again: set[str] = set()  # ... that changed again meanwhile
        self._stale: set[str] = set()  # documents the store went away from while catching up
        self._quiet_turn = False  # this turn of the event loop looked, and nothing had changed
        self._seen = store.log_head()  # the change log is followed from here; opens read the rest
        self.opens = self.hits = self.evictions = 0
        # What the open documents hold, kept up to date as they open, change and close, so that
        # keeping to the budget after each request is O(1), not a sum over every open document.
        self._held = 0
        self._sizes: dict[str, int] = {}  # each open document's bytes as counted in _held

    def __getitem__(self, doc_id: str) -> Document:
        """The document, opened if need be (blocking: call it from a worker thread).

        :raises NotFound: if there is no such document
        """
        doc = self._hit(doc_id)
        if doc is not None:
            return doc
        with self._lock:
            opening = self._opening.setdefault(doc_id, threading.Lock())
        try:
            with opening:  # a second request for it waits for the first's open
                with self._lock:
                    doc = self._open.get(doc_id)
                if doc is None:
                    doc = Document(self.store, self.files, self.store.document(doc_id))
                    doc.tiles.most = min(self.tile_bytes, max(self.budget // 4, 1 << 20))
                    # By weak reference: a cycle would keep a closed document, and its mapped
                    # snapshot file, until the cyclic collector ran (gen 2: rarely).
                    doc.on_publish = partial(self._recount, weakref.ref(doc))
                    with self._lock:
                        self._open[doc_id] = doc
                        self._count(doc)
                        self.opens += 1
                    # What committed while it opened was in the log before the follower could see it
                    doc.refresh()
        finally:  # opened or not (no such document): nothing of the id is kept
            with self._lock:
                self._opening.pop(doc_id, None)
        return doc

    async def get(self, doc_id: str) -> Document:
        """The document, opened in a worker thread if need be, up to date with the store.

        :raises NotFound: if there is no such document
        """
        await self.refresh()
        doc = self._open.get(doc_id)
        if doc is not None and doc.snapshot.broken and doc_id not in self._catching_up:
            self._catching_up[doc_id] = asyncio.create_task(self._catch_up(doc_id))  # rebuilt first
        catching_up = self._catching_up.get(doc_id)
        if catching_up is not None:  # it may be applying a write this request must see
            await asyncio.shield(catching_up)
        doc = self._hit(doc_id)
        return doc if doc is not None else await run_in_threadpool(self.__getitem__, doc_id)

    def _hit(self, doc_id: str) -> Document | None:
        """The document if it is open, marked the most recently used; else None."""
        with self._lock:
            doc = self._open.get(doc_id)
            if doc is not None:
                self._open.move_to_end(doc_id)
                self.hits += 1
            return doc

    async def refresh(self) -> None:
        """Catch the open documents up with what other processes wrote, as the store's change
        log tells: read from the last row seen (in a thread) when the store says something
        changed, one look at a time. Each document named is caught up by a task of its own
        (in a thread: mapping a new base, building one from the store, applying edits), which
        a request for that document waits for and no other does. While the store cannot be
        reached, documents answer as they are, and are tried again at the next look.

        One look per turn of the event loop: a request handled in the same turn as a look that
        found nothing was received before it, so no write it may need to see committed since."""
        if self._quiet_turn:
            return
        async with self._looking:
            if not self.store.changed():
                self._quiet_turn = True
                asyncio.get_running_loop().call_soon(self._next_turn)
                return
            try:
                changes = await run_in_threadpool(self.store.log_after, self._seen)
            except StoreUnavailable as error:
                log.debug("not caught up: %s", error.message)
                return
            if changes:
                self._seen = changes[-1].seq
            stale, self._stale = self._stale, set()
            for change in {change.doc_id: change for change in changes}.values():
                doc = self._open.get(change.doc_id)
                if doc is not None and (
                    change.kind in ("delete", "compact") or change.version > doc.snapshot.version
                ):
                    stale.add(change.doc_id)
            for doc_id in stale:
                if doc_id in self._catching_up:  # under way, maybe from before this change: again after
                    self._again.add(doc_id)
                else:
                    self._catching_up[doc_id] = asyncio.create_task(self._catch_up(doc_id))

    async def _catch_up(self, doc_id: str) -> None:
        """Catch one open document up with the store, again while the log says it changed meanwhile."""
        try:
            while True:
                self._again.discard(doc_id)
                doc = self._open.get(doc_id)
                if doc is None:
                    return
                try:
                    await run_in_threadpool(doc.refresh)
                except NotFound:  # deleted
                    self._close(doc_id, deleted=True)
                    return
                except StoreUnavailable as error:  # the next look tries again
                    self._stale.add(doc_id)
                    log.debug("%s not caught up: %s", doc_id, error.message)
                    return
                if doc_id not in self._again:
                    return
        finally:
            del self._catching_up[doc_id]

    async def settle(self) -> None:
        """Let the catching up under way end (before the store closes), then save each open
        document's edits not saved yet: the next start's opens replay none."""
        while self._catching_up:
            await asyncio.gather(*self._catching_up.values(), return_exceptions=True)
        with self._lock:
            saving = [doc.save_edits(every=1) for doc in self._open.values()]
        for thread in saving:
            if thread is not None:
                await asyncio.to_thread(thread.join)

    def save_old_edits(self, seconds: float) -> None:
        """Save, in the background, the edits of each open document whose first edit not saved
        yet is ``seconds`` old (``Document.save_edits_older_than``)."""
        with self._lock:
            documents = list(self._open.values())
        for doc in documents:
            doc.save_edits_older_than(seconds)

    def _next_turn(self) -> None:
        self._quiet_turn = False

    async def catch_up_to(self, doc: Document, version: int | None, patience: float) -> None:
        """Wait until ``doc`` shows ``version`` or later (None: any): catch it up with the store,
        trying again for up to ``patience`` seconds while the store cannot be reached. A version
        the store does not hold was never written (a write answers only once it committed).

        :raises Behind: if the store could not be reached in time
        :raises Conflict: if the store holds an older version: no such version exists yet
        """
        if version is None:
            return
        deadline = time.monotonic() + patience
        while doc.snapshot.version < version:
            try:
                await run_in_threadpool(doc.refresh)
            except StoreUnavailable:
                if time.monotonic() >= deadline:
                    raise Behind(
                        f"this server holds document {doc.id!r} at version {doc.snapshot.version}, not "
                        f"yet {version} (min_version), and cannot reach its store after "
                        f"{patience * 1000:.0f} ms (VANTAGE_CATCH_UP_MS): try again"
                    ) from None
                await asyncio.sleep(REACH_POLL_SECONDS)
                continue
            if doc.snapshot.version < version:
                raise Conflict(
                    f"min_version={version}, but document {doc.id!r} is at version "
                    f"{doc.snapshot.version}: no such version has been written"
                )

    def pinned(self, doc: Document) -> _Pin:
        """Keep ``doc`` open while the block runs (a request, a stream); then keep to the budget."""
        return _Pin(self, doc)

    def evict(self) -> None:
        """Close the least recently used documents not in use while the open ones hold more
        than the budget. The most recently used stays open: one bigger than the budget alone
        would otherwise be opened again for every request, its edits replayed each time. It
        closes when another document is used and needs the room."""
        with self._lock:
            if self._held <= self.budget:
                return
            for doc_id, doc in list(self._open.items())[:-1]:
                if self._held <= self.budget:
                    break
                if doc.pins == 0 and not doc._watchers:
                    del self._open[doc_id]
                    self._held -= self._sizes.pop(doc_id)
                    self.evictions += 1
                    doc.save_edits(every=1)  # its next open replays none

    def _count(self, doc: Document) -> None:
        """Count ``doc``'s bytes as they are now (under ``_lock``, ``doc`` open)."""
        size = doc.nbytes
        self._held += size - self._sizes.get(doc.id, 0)
        self._sizes[doc.id] = size

    def _recount(self, ref: weakref.ref[Document]) -> None:
        """The document shows a new snapshot: count its bytes again, if it is still open."""
        doc = ref()
        with self._lock:
            if doc is not None and self._open.get(doc.id) is doc:
                self._count(doc)

    def stats(self) -> dict[str, Any]:
        with self._lock:
            return {
                "worker": os.getpid(),
                "open": len(self._open),
                "held_bytes": self._held,
                "budget_bytes": self.budget,
                "opens": self.opens,
                "hits": self.hits,
                "evictions": self.evictions,
                "rebuilt": self.files.rebuilt,
            }

    def describe_all(self) -> list[dict[str, Any]]:
        """Every document: the open ones as they are, the others from the store's rows (whose
        bounds contain every item, exactly after an import)."""
        keys = ("id", "name", "created", "version", "items", "bounds")
        out = []
        for meta in self.store.documents():
            doc = self._open.get(meta["id"])
            out.append(doc.describe() if doc is not None else {k: meta[k] for k in keys})
        return out

    def create(self, name: str) -> Document:
        """:raises Conflict: if the store holds ``max_documents`` already"""
        return self[self.store.create_document(name, self.max_documents)["id"]]

    def delete(self, doc_id: str) -> None:
        """Delete the document and its files; its open streams are told (``Document.deleted``)."""
        doc = self[doc_id]
        with doc._edit_lock:
            self.store.delete_document(doc_id)
            self._close(doc_id, deleted=True)
        self.files.remove(doc_id)

    def _close(self, doc_id: str, deleted: bool = False) -> None:
        with self._lock:
            doc = self._open.pop(doc_id, None)
            if doc is not None:
                self._held -= self._sizes.pop(doc_id)
        if doc is not None and deleted:
            doc.deleted = True
            doc._publish(doc.snapshot)


class _Pin:
    """``Registry.pinned``'s context: a class, as every request takes one (a generator-based
    context costs ~1 µs more)."""

    __slots__ = ("doc", "registry")

    def __init__(self, registry: Registry, doc: Document) -> None:
        self.registry, self.doc = registry, doc

    def __enter__(self) -> Document:
        self.doc.pins += 1
        return self.doc

    def __exit__(self, *exc: object) -> None:
        doc = self.doc
        doc.pins -= 1
        registry = self.registry
        if registry._sizes.get(doc.id) != doc.nbytes:  # it made tiles: count them
            registry._recount(weakref.ref(doc))
        registry.evict()
