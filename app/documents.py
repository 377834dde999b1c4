"""One document: an immutable snapshot that queries run on, and the writes that replace it.

Queries read ``document.snapshot`` once and use only it, so an edit or import that swaps in a
new snapshot never shows a reader half of itself. A document opens by mapping its base's
snapshot file (rebuilt from the store when missing or corrupt) and applying the edits stored
since. Every write is one store transaction that first catches the document up with what other
processes stored, so no worker's write is lost or shown out of order.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from fastapi.concurrency import run_in_threadpool

from spatial.kernels import index_type
from spatial.paging import in_steps

from . import editfile
from .blocks import SnapshotCorrupt
from .errors import NotFound, StorageFull, TooMany, refused_when_full
from .heap import return_freed_memory
from .items import Batch, Columns, decode_item
from .snapfile import SnapshotFiles
from .snapshots import Snapshot, build, new_base_id
from .stores import Store
from .stores.base import Staged, bounds_of
from .table import ItemTable, Packed, Spill
from .tiles import Tiles

__all__ = ["Document", "pack"]

log = logging.getLogger("vantage.import")
Change = tuple[str, "tuple[float, ...] | None", "bytes | None"]  # item id, box, body (None: delete)
# The most items whose base an import builds in memory when its file cannot be written (a
# read-only directory, say; a full disk refuses the import): ~160 MB held for the 1M board; a
# larger one fails, storing nothing
IN_MEMORY_ITEMS = 1_000_000
SAVE_EDITS_EVERY = 2048  # edits made since they were last saved beside the base's file (``editfile``)
# Saves by age wait at least this many times as long as the last save took: one saving all of
# ~390k edits pending at 1e8 every 30 s would take a core's tenth or more
SAVE_WAITS_ITS_COST = 20


class Document:
    """One open document: its current snapshot, its writers' turn, and who watches it."""

    def __init__(self, store: Store, files: SnapshotFiles, meta: dict[str, Any]) -> None:
        self.store, self.files = store, files
        self.id, self.name, self.created = meta["id"], meta["name"], meta["created"]
        self._saving = threading.Lock()  # held while its edits are saved (``save_edits``)
        self._save_took = 0.0  # seconds the last save of its edits took
        # The base, and its edits last saved beside its file or opened from there
        self.edits_saved: tuple[str | None, int] = (None, 0)
        self.snapshot = self._caught_up(self._base(meta), meta)
        self._edit_lock = threading.Lock()  # edits serialise; readers never wait
        self._writing = asyncio.Lock()  # the same, for writers that wait on the event loop
        self._watchers: set[Callable[[], object]] = set()  # what they return is dropped
        self.deleted = False
        self.pins = 0  # requests in flight and open streams: while any, it stays open
        self.on_publish: Callable[[], object] | None = None  # the registry's count of its bytes
        self.tiles = Tiles()  # its zoomed-out answers' tiles: their bytes count as the document's
        # When the first edit not saved yet was shown: those it replayed, if any, are saved soon or now
        self._unsaved_since: float | None = time.monotonic()
        self.save_edits()  # an open that replayed many: the next one need not

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
        """What the document holds: its base (mapped or built), the edits since and its tiles."""
        snap = self.snapshot
        return snap.size + 300 * snap.edits + self.tiles.nbytes

    def needs_compaction(self) -> bool:
        """Whether enough edits piled up since the base to fold them into a new one."""
        return self.snapshot.needs_compaction

    async def write(self, edit: Callable[..., Any], *args: Any) -> Any:
        """``edit(*args)`` in a worker thread once the writes before it are done: the
        document's, then the store's (``Store.turn``, as far as its engine makes writers take
        turns). Writers queue here, on the event loop, so a long write never lets them fill
        the thread pool that every other document's requests need."""
        async with self._writing, self.store.turn:
            return await run_in_threadpool(edit, *args)

    async def write_import(
        self, imported: ItemTable, max_items: int | None, replace: bool
    ) -> tuple[int, int]:
        """``import_table`` from the event loop: built outside the store's turn, which other
        documents' writers take meanwhile (this one's wait); built again inside it if another
        process wrote the document meanwhile."""
        async with self._writing:
            done = await run_in_threadpool(self._import_beside, imported, max_items, replace)
            if done is None:
                async with self.store.turn:
                    done = await run_in_threadpool(self._import_inside, imported, max_items, replace)
            return done

    def watch(self, callback: Callable[[], object]) -> Callable[[], None]:
        """Call ``callback`` (from the editing thread) after each new version; returns the unwatch."""
        self._watchers.add(callback)
        return lambda: self._watchers.discard(callback)

    def import_items(
        self, batches: Iterable[Batch], max_items: int | None = None, *, replace: bool = False
    ) -> tuple[int, int]:
        """Store the items of ``batches`` all or nothing (upsert by id, or ``replace`` what the
        document held), then show them; ``(distinct items imported, version)``. If iterating
        ``batches`` raises, nothing changes."""
        return self.import_table(pack(batches, self.files.directory), max_items, replace=replace)

    def import_table(
        self, imported: ItemTable, max_items: int | None = None, *, replace: bool = False
    ) -> tuple[int, int]:
        """Store ``imported`` (from ``pack``) all or nothing, upserting by id (with ``replace``:
        instead of what the document held), then show it; ``(distinct items imported,
        version)``. An import with nothing (a compaction) folds the edits into a new base.

        Built outside any write (``_import_beside``): its writers (another document's on
        SQLite, every one) do not wait for it. If another process wrote the document meanwhile,
        it is built again inside one write (``_import_inside``), which they then wait for.

        :raises TooMany: if the document would hold more than ``max_items``
        """
        done = self._import_beside(imported, max_items, replace)
        return done if done is not None else self._import_inside(imported, max_items, replace)

    @refused_when_full("building the import's new base")
    def _import_beside(
        self, imported: ItemTable, max_items: int | None, replace: bool
    ) -> tuple[int, int] | None:
        """The import merged with the document as the store holds it now, its base built
        straight into its snapshot file (in memory if that cannot be written and it is small:
        ``_built``) while its rows are staged on the other core (``Store.stage_base``),
        outside any write; then one short write makes it the next version and drops the edits
        (the old base's rows go after). None, with nothing stored, if another process wrote
        the document meanwhile."""
        base_id, staged, stored = new_base_id(), None, False
        try:
            with self._edit_lock:
                meta = self.store.document(self.id)
                step = _Steps(f"import into {self.id}")
                table = self._import_merged(
                    self._caught_up(self.snapshot, meta), imported, max_items, replace
                )
                step("to merge the items")
                version, bounds = meta["version"] + 1, bounds_of(table.read_boxes())
                log.info("import into %s: storing %d items (worker %d)", self.id, len(table), os.getpid())
                built, staged = self._built_and_staged(table, version, base_id, step)
                step("to finish the store's rows")
                with self.store.writing(self.id) as write:
                    meta = dict(write.meta)
                    if meta["version"] != version - 1:  # another process's write: built on a stale state
                        log.info(
                            "import into %s: the document changed meanwhile: built again in a write", self.id
                        )
                        return None
                    write.bump()
                    old_rows = write.import_base(staged, version, base_id, len(table), bounds)
                stored = True
                step("to commit")
                del table
        finally:
            if not stored:
                self.files.remove(self.id, base_id)
                if staged is not None:
                    self._drop_rows(staged.rowset)
        self._show(built, meta, version, base_id)
        self._drop_rows(old_rows)
        self.store.checkpoint()
        return len(imported), version

    @refused_when_full("building the import's new base")
    def _import_inside(self, imported: ItemTable, max_items: int | None, replace: bool) -> tuple[int, int]:
        """The import inside one write, merged with the document as the store holds it there:
        the document's writers (on SQLite, every writer) wait for the whole of it."""
        base_id = new_base_id()
        try:
            with self._edit_lock, self.store.writing(self.id) as write:
                meta = dict(write.meta)
                step = _Steps(f"import into {self.id}")
                snap = self._caught_up(self.snapshot, meta, writing=True)
                table = self._import_merged(snap, imported, max_items, replace)
                step("to merge the items")
                log.info("import into %s: storing %d items (worker %d)", self.id, len(table), os.getpid())
                version = write.bump()
                # The store's rows (compression and I/O, on the other core) while the index is
                # built: they need only the table. The transaction waits for them either way.
                with ThreadPoolExecutor(1) as beside:
                    bounds = bounds_of(table.read_boxes())
                    storing = beside.submit(write.write_base, table, version, base_id, bounds)
                    built = self._built(table, version, base_id, step)
                    storing.result()
                step("to finish the store's rows")
            step("to commit")
            del table
        except BaseException:  # not stored (a full disk, a kill): its file must not outlive it
            self.files.remove(self.id, base_id)
            raise
        self._show(built, meta, version, base_id)
        self.store.checkpoint()
        return len(imported), version

    def _import_merged(
        self, snap: Snapshot, imported: ItemTable, max_items: int | None, replace: bool
    ) -> ItemTable:
        """``imported`` merged with what ``snap`` shows (upserted by id), or alone (``replace``).

        :raises TooMany: if it holds more than ``max_items``
        """
        current = self._items(snap) if len(snap.tree) and not replace else None
        tables = [t for t in (current, imported) if t is not None and len(t)] or [imported]
        table = self._merged(tables)
        if max_items is not None and len(table) > max_items:
            raise TooMany(
                f"the document would hold {len(table)} items; the most is {max_items} (VANTAGE_MAX_ITEMS)"
            )
        return table

    def _built(
        self, table: ItemTable, version: int, base_id: str, step: _Steps, in_memory: bool = True
    ) -> Snapshot | None:
        """The base of ``table`` built straight into its snapshot file (None: mapped once
        stored, its pages shared with every other worker), or in memory if that fails (an
        import's, of up to ``IN_MEMORY_ITEMS``). Otherwise a file not written stops it: built
        in memory the whole index is held at once (over 12 GB at 1e8 items), and a compaction's
        document needs no new base to answer.

        :raises OSError: if the file could not be written, without ``in_memory``, or the disk
            is full (never built in memory then: the store, on that disk too, is full)
        :raises StorageFull: if it could not be written for an import of more items
        """
        if self.files.write(self.id, table, version, base_id, True):  # True: a full disk raised
            step("to build the index into its snapshot file")
            return None
        if not in_memory:
            raise OSError(f"the new base's snapshot file of {self.id} could not be written (see above)")
        if len(table) > IN_MEMORY_ITEMS:
            raise StorageFull(
                f"the snapshot file of {self.id}'s new base could not be written (the log says why: "
                f"a full disk?), and {len(table):,} items are more than an import builds in "
                f"memory instead ({IN_MEMORY_ITEMS:,}): nothing was stored; free some space"
            )
        built = build(table, version, base_id)
        step("to build the index in memory")
        return built

    def _built_and_staged(
        self, table: ItemTable, version: int, base_id: str, step: _Steps, in_memory: bool = True
    ) -> tuple[Snapshot | None, Staged]:
        """``_built``, while the store's rows are staged on the other core
        (``Store.stage_base``); the staged rows go again if the build fails.

        :raises: what the build or the staging raised (a staging drops its own rows)
        """
        with ThreadPoolExecutor(1) as beside:
            staging = beside.submit(self.store.stage_base, self.id, table)
            try:
                built = self._built(table, version, base_id, step, in_memory)
            except BaseException:
                if staging.exception() is None:  # waits for it: then its rows are no base's
                    self._drop_rows(staging.result().rowset)
                raise
            return built, staging.result()

    def _show(self, built: Snapshot | None, meta: dict[str, Any], version: int, base_id: str) -> None:
        """Show the new base stored at ``version`` (``built``, or mapped from its file), its
        document's row ``meta`` as the write found it; remove the file of the base it replaced."""
        if built is None:
            built = self.files.base(self.store, {**meta, "base_id": base_id, "base_version": version})
        self._publish(built)
        if meta["base_id"] is not None:
            self.files.remove(self.id, meta["base_id"])
        del built
        return_freed_memory()

    def _items(self, snap: Snapshot) -> ItemTable:
        """The items ``snap`` shows, as a table: its base's table with the stored edits since
        put in (the rows are read only when a block of the base's file is found bad)."""
        spill = self.files.directory
        # a fold is a build in files too: its windows held to the budget of a build of its items
        with self.files.budget(len(snap.table)).held():
            try:
                if (table := snap.stored_table(spill)) is None:
                    table = snap.document_table(spill, self.store.edits(self.id))
                return table
            except SnapshotCorrupt:
                return self.store.read_items(self.id, spill=spill)

    def _merged(self, tables: list[ItemTable]) -> ItemTable:
        """``tables`` merged (``ItemTable.merge``), its id index halved and spilled: ready to build."""
        with self.files.budget(sum(map(len, tables))).held():  # its sorts and windows, in files
            table = ItemTable.merge(tables, spill=self.files.directory)
            table.halve_hashes(self.files.directory)  # merged: only looked up from now on
            return table.spilled(self.files.directory)  # what the merge made, the halved hashes

    @refused_when_full("building the compaction's new base")
    def compact(self) -> int:
        """Fold the edits since the base into a new base (and file); the version, which does
        not change (nor do the items).

        The new base is built outside the writers' turn, from the snapshot shown when it began
        (version V): edits go on meanwhile. Its rows are staged in the store meanwhile too, on
        the other core, a short transaction a row (``Store.stage_base``). Then one short write
        points the document at them and drops the edits up to V; those since stay, applied on
        the new base as on any. If an import (or another process's compaction) replaced the
        base meanwhile, nothing is stored. The base may hold some edits made after V (the store
        keeps each item's last edit only): they are applied again, which changes nothing. The
        old base's rows go last, a row at a time.

        :raises StorageFull: if the disk is full; OSError: if the new base's file could not be
            written otherwise; either way nothing is stored, and the edits stay for the next one
        """
        snap, base_id = self.snapshot, new_base_id()
        if not snap.edits:
            return snap.version
        step = _Steps(f"compaction of {self.id}")
        staged: Staged | None = None
        stored = False
        try:
            table = self._merged([self._items(snap)])
            step("to fold the edits into the items")
            _, staged = self._built_and_staged(table, snap.version, base_id, step, in_memory=False)
            step("to stage its rows (edits went on meanwhile)")
            with self._edit_lock, self.store.writing(self.id) as write:
                meta = dict(write.meta)
                if meta["base_id"] != snap.base_id:  # replaced meanwhile: this one is stale
                    log.info("compaction of %s dropped: its base was replaced meanwhile", self.id)
                    self.files.remove(self.id, base_id)
                    return meta["version"]
                old_rows = write.compact_base(staged, snap.version, base_id)
                meta.update(base_id=base_id, base_version=snap.version)
                base = self.files.base(self.store, meta, name=False)
                fresh = self._caught_up(base, meta, writing=True)  # the edits made meanwhile
            stored = True
            step("to store the new base")
        except BaseException:
            self.files.remove(self.id, base_id)
            raise
        finally:
            if staged is not None and not stored:  # staged, never the base's
                self._drop_rows(staged.rowset)
        self._publish(fresh)
        if snap.base_id is not None:
            self.files.remove(self.id, snap.base_id)
        self._drop_rows(old_rows)
        self.store.checkpoint()
        step("to drop the old base's rows")
        del table
        return_freed_memory()
        return fresh.version

    def _drop_rows(self, rowset: int) -> None:
        """Delete the rows of ``rowset``, no longer (or never) the base's; if the store is
        away (or fails), the sweep at the next start deletes them (``Store.sweep_rows``)."""
        try:
            self.store.drop_rows(self.id, rowset)
        except Exception as error:  # upkeep, maybe while another error is raised: never masks it
            log.warning("the rows of a replaced base of %s are left for the next sweep: %s", self.id, error)

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
        """Catch up with what other processes stored since this snapshot, and show it; build
        the base again if a read found its file corrupt."""
        with self._edit_lock:
            snap = self._caught_up(self.snapshot, self.store.document(self.id))
            if snap is not self.snapshot:
                self._publish(snap)

    def _caught_up(self, snap: Snapshot, meta: dict[str, Any], writing: bool = False) -> Snapshot:
        """``snap`` brought to the store's state ``meta``: another base mapped (or its own built
        again when a read found its file corrupt), newer edits applied."""
        corrupt = snap.broken if meta["base_id"] == snap.base_id else None
        if corrupt or meta["base_id"] != snap.base_id or meta["base_version"] > snap.version:
            snap = self._base(meta, name=not writing, corrupt=corrupt)
        if meta["version"] > snap.version:
            try:
                snap, _ = snap.with_edits(self.store.edits(meta["id"], after=snap.version))
            except SnapshotCorrupt:
                if snap.broken is None:  # no block of this base's file was found bad: not damage
                    raise
                return self._caught_up(snap, meta, writing)  # its base built again, then edited
        return snap

    def _base(self, meta: dict[str, Any], name: bool = True, corrupt: str | None = None) -> Snapshot:
        """The document's base (``SnapshotFiles.base``), with the edits saved beside its file
        made again (``editfile``) if they are there and follow the store's: the store's since
        are then replayed, not all since the base. A file that does not is removed."""
        base = self.files.base(self.store, meta, name=name, corrupt=corrupt)
        if base.blocks is None:  # looked for with no edits since the base too: one newer is removed
            return base
        path = self.files.edits_path(self.id, str(base.base_id))
        saved = editfile.load(path, base, meta["version"], self.store, self.id)
        if saved is None:
            return base
        self.edits_saved = (saved.base_id, saved.edits)
        return saved

    def save_edits(self, every: int | None = None) -> threading.Thread | None:
        """Save the edits of the snapshot shown beside its base's file (``editfile``), in the
        background, if ``every`` (``SAVE_EDITS_EVERY``) more were made since the last saved
        (1: when the document closes); the thread saving them, if one does. An open then
        replays fewer than that from the store. Not past the tree's buffer: the tree has
        rebuilt itself in memory, as large as the document, and a compaction is due."""
        snap = self.snapshot
        base_id, saved = self.edits_saved
        since = snap.edits - (saved if base_id == snap.base_id else 0)
        every = SAVE_EDITS_EVERY if every is None else every
        if snap.blocks is None or not since or snap.edits >= snap.tree.max_buffered:
            self._unsaved_since = None  # none to save, or none that can be
            return None
        if since < every or not self._saving.acquire(blocking=False):  # one at a time: tried again
            return None
        before, self.edits_saved = self.edits_saved, (snap.base_id, snap.edits)
        self._unsaved_since = None if self.snapshot is snap else time.monotonic()  # one shown since

        def save() -> None:
            path, start = self.files.edits_path(self.id, str(snap.base_id)), time.monotonic()
            try:
                if (editfile.saved_version(path) or -1) < snap.version:  # another worker's may be newer
                    editfile.save(path, snap, self.store, self.id)
            except Exception as error:  # a cache (a full disk, the store away): the store holds the edits
                log.warning("the edits of %s were not saved beside its base: %s", self.id, error)
                if self.edits_saved == (snap.base_id, snap.edits):  # none saved since: tried again by age
                    self.edits_saved = before
                if self._unsaved_since is None:
                    self._unsaved_since = time.monotonic()
            finally:
                self._save_took = time.monotonic() - start
                self._saving.release()

        thread = threading.Thread(target=save, name=f"save edits of {self.id}", daemon=True)
        thread.start()
        return thread

    def save_edits_older_than(self, seconds: float) -> threading.Thread | None:
        """``save_edits`` of every edit not saved yet, once the first of them is ``seconds``
        old, or ``SAVE_WAITS_ITS_COST`` times what the last save took if longer: what a crash
        leaves to replay is bounded in time, not only in count, and saves take a small share
        of a core."""
        first, wait = self._unsaved_since, max(seconds, SAVE_WAITS_ITS_COST * self._save_took)
        return None if first is None or time.monotonic() - first < wait else self.save_edits(every=1)

    def _publish(self, snap: Snapshot) -> None:
        """Show ``snap``, unless a newer one is shown already (a catch-up that ran between a
        write's commit and its publishing)."""
        if snap.version < self.snapshot.version:
            return
        self.snapshot = snap
        if self._unsaved_since is None:
            self._unsaved_since = time.monotonic()
        self.save_edits()
        if self.on_publish is not None:
            self.on_publish()
        for callback in list(self._watchers):
            callback()


class _Steps:
    """Logs each step of a long write as it ends, with the seconds it took: what an import of
    millions of items is doing once its items are read."""

    def __init__(self, what: str) -> None:
        self.what, self.since = what, time.monotonic()

    def __call__(self, done: str) -> None:
        now = time.monotonic()
        log.info("%s: %.1f s %s", self.what, now - self.since, done)
        self.since = now


@refused_when_full("spilling the import's items")
def pack(batches: Iterable[Batch | Columns], spill: Path | None = None) -> ItemTable:
    """The items of ``batches`` as one table, a repeated id keeping its last box (an upsert).
    Packed a batch at a time: a million Python strings at once would linger as heap. With
    ``spill``, a directory, the bodies, ids and boxes and their offsets are written to a
    ``Spill`` there as they come, and once packed the id index goes to one too
    (``ItemTable.spilled``): memory then holds none of the items' columns, only the pages a
    pass reads, and the index while it is made.

    :raises: whatever iterating ``batches`` raises (a bad line, say)
    """
    parts = (batch.columns() for batch in batches)
    if spill is None:
        tables = [
            ItemTable(_packed(p.ids, p.id_ends), _packed(p.bodies, p.body_ends), p.boxes) for p in parts
        ]
        return ItemTable.merge(tables or [ItemTable.empty()])
    with contextlib.ExitStack() as stack:
        bodies, ids, boxes, body_offsets, id_offsets = (stack.enter_context(Spill(spill)) for _ in range(5))
        for offsets in (body_offsets, id_offsets):
            offsets.write(np.zeros(1, np.int64).data)
        for part in parts:  # each column, its offsets too, written as it comes: none held
            body_offsets.write((part.body_ends + bodies.size).astype(np.int64).data)
            bodies.write(part.bodies)
            id_offsets.write((part.id_ends + ids.size).astype(np.int64).data)
            ids.write(part.ids)
            boxes.write(np.ascontiguousarray(part.boxes, np.float64).reshape(-1).view(np.uint8).data)
        if not boxes.size:
            return ItemTable.empty()
        table = ItemTable(
            # The ids' offsets int32 while they fit, as a snapshot file keeps them
            Packed(ids.mapped(), _narrowed(_mapped(id_offsets, np.int64), index_type(ids.size), spill)),
            Packed(bodies.mapped(), _mapped(body_offsets, np.int64)),
            _mapped(boxes, np.float64).reshape(-1, 4),
        )
    return_freed_memory()  # the decoded batches' heap
    return ItemTable.merge([table], spill=spill).spilled(spill)  # the id index paged as the rest


def _mapped(spilled: Spill, dtype: type[np.generic]) -> np.ndarray:
    return np.frombuffer(spilled.mapped(), dtype)


def _narrowed(offsets: np.ndarray, dtype: type[np.signedinteger], spill: Path) -> np.ndarray:
    """Mapped ``offsets`` in ``dtype``: as they are, or copied a step at a time to a ``Spill``
    in ``spill`` (each step's pages handed back)."""
    if offsets.dtype == dtype:
        return offsets
    with Spill(spill) as out:
        for _, step in in_steps(offsets):
            out.write(step.astype(dtype).data)
        return _mapped(out, dtype)


def _packed(buffer: bytes, ends: np.ndarray) -> Packed:
    return Packed(buffer, np.concatenate((np.zeros(1, np.int64), ends)))


def _grown(bounds: list[float] | None, box: tuple[float, ...]) -> tuple[float, ...]:
    if bounds is None:
        return box
    return (min(bounds[0], box[0]), min(bounds[1], box[1]), max(bounds[2], box[2]), max(bounds[3], box[3]))
