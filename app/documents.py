"""Documents: each an immutable snapshot that queries run on, opened on demand within a memory
budget, and kept up to date with what any process writes to the store.

Queries read ``document.snapshot`` once and use only it, so an edit or import that swaps in a
new snapshot never shows a reader half of itself. A document opens by mapping its base's
snapshot file (rebuilt from the store when missing or corrupt) and applying the edits stored
since; it stays open while it is used, and the least recently used ones close when the open
ones hold more than the budget. Every write is one store transaction that first catches the
document up with what other processes stored, so no worker's write is lost or shown out of
order; other workers catch up when the store says something changed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from functools import partial
from pathlib import Path
from typing import Any

import msgspec
from fastapi.concurrency import run_in_threadpool

from . import snapshots
from .errors import Behind, Conflict, NotFound, TooMany
from .housekeeping import return_freed_memory
from .items import Batch, decode_item
from .snapfile import SnapshotFileError, SnapshotFileMissing
from .snapshots import Snapshot, build, new_base_id
from .stores import Store, StoreUnavailable
from .table import ItemTable

__all__ = ["Document", "Registry", "SnapshotFiles", "pack"]

log = logging.getLogger("vantage.import")
Change = tuple[str, "tuple[float, ...] | None", "bytes | None"]  # item id, box, body (None: delete)
REACH_POLL_SECONDS = 0.02  # how often a request waiting for a version looks again
SWEEP_GRACE_SECONDS = 3600.0  # a snapshot file of no current base younger than this is left alone
COMPACT_AFTER = 1024  # edits since the base (plus one per 256 items) before they are folded into a new one


class SnapshotFiles:
    """Where snapshot files live (``<doc>.<base_id>.vsnap``), and opening a document from one."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.rebuilt = 0  # files found stale or corrupt, and built again from the store

    def path(self, doc_id: str, base_id: str) -> Path:
        return self.directory / f"{doc_id}.{base_id}.vsnap"

    def save(self, doc_id: str, snap: Snapshot) -> bool:
        """Write ``snap``'s file; False (logged) if it could not be: it is a cache, the store is the truth."""
        try:
            snapshots.save(snap, self.path(doc_id, snap.base_id))  # type: ignore[arg-type]
            return True
        except OSError as error:
            log.warning("could not write the snapshot file of %s: %s", doc_id, error)
            return False

    def base(self, store: Store, meta: dict[str, Any], name: bool = True) -> Snapshot:
        """The snapshot of the document's base (no edits): mapped from its file, else built
        from the store and saved, then mapped. A base without a name gets one first (``meta``
        is updated with it), unless not ``name``: inside a write, which replaces it anyway."""
        doc_id, base_id, version = meta["id"], meta["base_id"], meta["base_version"]
        if base_id is not None:
            try:
                return snapshots.load(self.path(doc_id, base_id), base_id, version)
            except SnapshotFileMissing:  # as on a replica's first open: its files are its own cache
                log.info("snapshot of %s built from the store: no file for it here yet", doc_id)
            except SnapshotFileError as error:
                log.warning("snapshot of %s rebuilt from the store: %s", doc_id, error)
                self.rebuilt += 1
        table = store.read_base(doc_id)
        if not len(table) or (base_id is None and not name):
            return build(table, version, base_id)
        if base_id is None:  # written without a server, or before snapshot files: name its base
            with store.writing(doc_id) as write:
                write.set_base_id(new_base_id())
            meta.update(store.document(doc_id))  # ours, or another process's that named it first
            return self.base(store, meta)
        built = build(table, version, base_id)
        if not self.save(doc_id, built):
            return built
        try:
            return snapshots.load(self.path(doc_id, base_id), base_id, version)
        except SnapshotFileError:
            return built

    def sweep(self, store: Store, grace: float = SWEEP_GRACE_SECONDS) -> int:
        """Remove the files of no document's current base (a process killed mid-import left
        them, or one that wrote its file but not its base), and half-written ``.tmp`` files,
        older than ``grace`` seconds: a younger one may be an import's about to commit. The
        number removed."""
        current = {f"{d['id']}.{d['base_id']}.vsnap" for d in store.documents()}
        cutoff, removed = time.time() - grace, 0
        for path in [*self.directory.glob("*.vsnap"), *self.directory.glob(".*.vsnap.*.tmp")]:
            with contextlib.suppress(OSError):  # gone already: another worker swept it
                if path.name not in current and path.stat().st_mtime < cutoff:
                    path.unlink()
                    removed += 1
        if removed:
            log.info("removed %d snapshot files of no current base from %s", removed, self.directory)
        return removed

    def remove(self, doc_id: str, base_id: str | None = None) -> None:
        """Remove a document's file of ``base_id``, or all of them. A process that still maps
        one keeps it until it lets go: removing a mapped file is safe."""
        for path in self.directory.glob(f"{doc_id}.{base_id or '*'}.vsnap"):
            path.unlink(missing_ok=True)


class Document:
    """One open document: its current snapshot, its writers' turn, and who watches it."""

    def __init__(self, store: Store, files: SnapshotFiles, meta: dict[str, Any]) -> None:
        self.store, self.files = store, files
        self.id, self.name, self.created = meta["id"], meta["name"], meta["created"]
        self.snapshot = self._caught_up(files.base(store, meta), meta)
        self._edit_lock = threading.Lock()  # edits serialise; readers never wait
        self._writing = asyncio.Lock()  # the same, for writers that wait on the event loop
        self._watchers: set[Callable[[], None]] = set()
        self.deleted = False
        self.pins = 0  # requests in flight and open streams: while any, it stays open
        self.on_publish: Callable[[], object] | None = None  # the registry's count of its bytes

    def describe(self) -> dict[str, Any]:
        snap = self.snapshot
        return {
            "id": self.id,
            "name": self.name,
            "created": self.created,
            "version": snap.version,
            "items": len(snap.tree),
            "bounds": snap.bounds,
        }

    @property
    def nbytes(self) -> int:
        """What the document holds: its base (mapped or built) and the edits since."""
        snap = self.snapshot
        return snap.size + 300 * snap.edits

    def needs_compaction(self) -> bool:
        """Whether enough edits piled up since the base to fold them into a new one."""
        snap = self.snapshot
        return snap.edits > COMPACT_AFTER + len(snap.table) // 256

    async def write(self, edit: Callable[..., Any], *args: Any) -> Any:
        """``edit(*args)`` in a worker thread once the writes before it are done: the store's
        (``Store.turn``, as far as its engine makes writers take turns) and the document's.
        Writers queue here, on the event loop, so a long import never lets them fill the
        thread pool that every other document's requests need."""
        async with self.store.turn, self._writing:
            return await run_in_threadpool(edit, *args)

    def watch(self, callback: Callable[[], None]) -> Callable[[], None]:
        """Call ``callback`` (from the editing thread) after each new version; returns the unwatch."""
        self._watchers.add(callback)
        return lambda: self._watchers.discard(callback)

    def import_items(
        self, batches: Iterable[Batch], max_items: int | None = None, *, replace: bool = False
    ) -> tuple[int, int]:
        """Store the items of ``batches`` all or nothing (upsert by id, or ``replace`` what the
        document held), then show them; ``(distinct items imported, version)``. If iterating
        ``batches`` raises, nothing changes."""
        return self.import_table(pack(batches), max_items, replace=replace)

    def import_table(
        self, imported: ItemTable, max_items: int | None = None, *, replace: bool = False
    ) -> tuple[int, int]:
        """Store ``imported`` (from ``pack``) all or nothing, upserting by id (with ``replace``:
        instead of what the document held), then show it.

        Inside one store transaction: merge with the document as the store holds it, build
        the new base's snapshot and write its file (so any process that sees the commit finds
        it), store the base, commit; only then show it. An import with nothing (a compaction)
        folds the edits into a new base.

        :raises TooMany: if the document would hold more than ``max_items``
        """
        old, base_id = self.snapshot.base_id, new_base_id()
        try:
            with self._edit_lock, self.store.writing(self.id) as write:
                meta = dict(write.meta)
                snap = self._caught_up(self.snapshot, meta, writing=True)
                keep = len(snap.tree) and not replace
                current = (snap.stored_table() or self.store.read_items(self.id)) if keep else None
                table = ItemTable.merge([current, imported] if current is not None else [imported])
                if max_items is not None and len(table) > max_items:
                    raise TooMany(
                        f"the document would hold {len(table)} items; the most is {max_items} (VANTAGE_MAX_ITEMS)"
                    )
                log.info("import into %s: storing %d items (worker %d)", self.id, len(table), os.getpid())
                version = write.bump()
                built = build(table, version, base_id)
                saved = self.files.save(self.id, built)
                write.write_base(table, version, base_id, built.bounds)
        except BaseException:  # not stored (a full disk, a kill): its file must not outlive it
            self.files.remove(self.id, base_id)
            raise
        if saved:  # serve the mapped file: its pages are shared with every other worker
            meta = {**meta, "base_id": built.base_id, "base_version": version}
            built = self.files.base(self.store, meta)
        self._publish(built)
        if old is not None:
            self.files.remove(self.id, old)
        self.store.checkpoint()
        count = len(imported)
        del current, table, imported, built
        return_freed_memory()
        return count, version

    def compact(self) -> int:
        """Fold the edits since the base into a new base (and file); the version."""
        return self.import_table(ItemTable.empty())[1]

    def put(self, item: Batch, max_items: int | None = None) -> tuple[int, bool]:
        """Store and show one item (a batch of one); ``(version, created)``.

        :raises TooMany: if it is new and the document already holds ``max_items``
        """
        (item_id,), (body,) = item.ids, item.bodies
        version, (created,) = self.edit([(item_id, tuple(item.boxes[0].tolist()), body)], max_items)
        return version, created

    def delete(self, item_id: str) -> int:
        """Delete one item; the version.

        :raises NotFound: if it is not there
        """
        return self.edit([(item_id, None, None)])[0]

    def patch(self, item_id: str, fields: dict[str, Any], max_data_bytes: int) -> int:
        """Change some of one item's fields (``data: null`` drops its data); the version.
        Merged with the item as it stands inside the write, so a concurrent edit of its other
        fields is never undone.

        :raises NotFound: if it is not there
        :raises ItemError: if the merged item is invalid
        """

        def change(snap: Snapshot) -> list[Change]:
            pos = snap.position(item_id)
            if pos is None:
                raise NotFound(f"item {item_id!r} not found in document {self.id!r}")
            merged = {**msgspec.json.decode(snap.item_json(pos)), **fields, "id": item_id}
            if merged.get("data", ...) is None:
                del merged["data"]
            item = decode_item(msgspec.json.encode(merged), max_data_bytes, item_id)
            return [(item_id, tuple(item.boxes[0].tolist()), item.bodies[0])]

        return self.edit(change)[0]

    def edit(
        self, changes: list[Change] | Callable[[Snapshot], list[Change]], max_items: int | None = None
    ) -> tuple[int, list[bool]]:
        """Store and show ``changes``, ``(item id, box, body)`` each (box and body None: delete),
        all or nothing, as one version; ``(version, created)``, created saying of each change
        whether it made a new item. ``changes`` may be a function of the snapshot as it stands
        in the write (a patch reads the item it changes).

        :raises NotFound: if a deletion names items that are not there (all named, up to five)
        :raises TooMany: if the document would hold more than ``max_items``
        """
        with self._edit_lock, self.store.writing(self.id) as write:
            meta = dict(write.meta)
            snap = self._caught_up(self.snapshot, meta, writing=True)
            if callable(changes):
                changes = changes(snap)
            live = {item_id: snap.position(item_id) is not None for item_id, _, _ in changes}
            missing = [i for i, box, _ in changes if box is None and not live[i]]
            if missing:
                named = ", ".join(map(repr, missing[:5])) + (
                    f" and {len(missing) - 5} more" if len(missing) > 5 else ""
                )
                raise NotFound(f"no item {named} in document {self.id!r}: nothing was deleted")
            created, seen = [], set()
            for item_id, box, _ in changes:
                created.append(box is not None and not live[item_id] and item_id not in seen)
                seen.add(item_id)
            if max_items is not None and any(created) and len(snap.tree) + sum(created) > max_items:
                raise TooMany(
                    f"the document holds {len(snap.tree)} items, the most it may (VANTAGE_MAX_ITEMS)"
                )
            version = write.bump()
            edited, _ = snap.with_edits([(i, version, box, body) for i, box, body in changes])
            bounds = meta["bounds"]
            for _, box, _ in changes:
                bounds = bounds if box is None else _grown(bounds, box)
            write.write_edits(version, changes, len(edited.tree), bounds)
        self._publish(edited)
        return version, created

    def refresh(self) -> None:
        """Catch up with what other processes stored since this snapshot, and show it."""
        with self._edit_lock:
            snap = self._caught_up(self.snapshot, self.store.document(self.id))
            if snap is not self.snapshot:
                self._publish(snap)

    def _caught_up(self, snap: Snapshot, meta: dict[str, Any], writing: bool = False) -> Snapshot:
        """``snap`` brought to the store's state ``meta``: another base mapped, newer edits applied."""
        if meta["base_id"] != snap.base_id or meta["base_version"] > snap.version:
            snap = self.files.base(self.store, meta, name=not writing)
        if meta["version"] > snap.version:
            snap, _ = snap.with_edits(self.store.edits(meta["id"], after=snap.version))
        return snap

    def _publish(self, snap: Snapshot) -> None:
        """Show ``snap``, unless a newer one is shown already (a catch-up that ran between a
        write's commit and its publishing)."""
        if snap.version < self.snapshot.version:
            return
        self.snapshot = snap
        if self.on_publish is not None:
            self.on_publish()
        for callback in list(self._watchers):
            callback()


class Registry:
    """The store's documents, opened on demand: those used most recently stay open while the
    open ones hold at most ``budget`` bytes; one in use (a request, a stream) never closes."""

    def __init__(
        self, store: Store, files: SnapshotFiles, budget: int, max_documents: int | None = None
    ) -> None:
        self.store, self.files, self.budget, self.max_documents = store, files, budget, max_documents
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
                    doc.on_publish = partial(self._recount, doc)
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
        catching_up = self._catching_up.get(doc_id)
        if catching_up is not None:  # it may be applying a write this request must see
            await asyncio.shield(catching_up)
        return self._hit(doc_id) or await run_in_threadpool(self.__getitem__, doc_id)

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
                if doc is not None and (change.kind == "delete" or change.version > doc.snapshot.version):
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
        """Let the catching up under way end (before the store closes)."""
        while self._catching_up:
            await asyncio.gather(*self._catching_up.values(), return_exceptions=True)

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
        than the budget."""
        with self._lock:
            if self._held <= self.budget:
                return
            for doc_id, doc in list(self._open.items()):
                if self._held <= self.budget:
                    break
                if doc.pins == 0 and not doc._watchers:
                    del self._open[doc_id]
                    self._held -= self._sizes.pop(doc_id)
                    self.evictions += 1

    def _count(self, doc: Document) -> None:
        """Count ``doc``'s bytes as they are now (under ``_lock``, ``doc`` open)."""
        size = doc.nbytes
        self._held += size - self._sizes.get(doc.id, 0)
        self._sizes[doc.id] = size

    def _recount(self, doc: Document) -> None:
        """``doc`` shows a new snapshot: count its bytes again, if it is still open."""
        with self._lock:
            if self._open.get(doc.id) is doc:
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


def pack(batches: Iterable[Batch]) -> ItemTable:
    """The items of ``batches`` as one table, a repeated id keeping its last box (an upsert).
    Packed a batch at a time: a million Python strings at once would linger as heap.

    :raises: whatever iterating ``batches`` raises (a bad line, say)
    """
    return ItemTable.merge([ItemTable.of(b.ids, b.boxes, b.bodies) for b in batches] or [ItemTable.empty()])


def _grown(bounds: list[float] | None, box: tuple[float, ...]) -> tuple[float, ...]:
    if bounds is None:
        return box
    return (min(bounds[0], box[0]), min(bounds[1], box[1]), max(bounds[2], box[2]), max(bounds[3], box[3]))


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
        self.doc.pins -= 1
        self.registry.evict()
