"""Snapshot files: where a document's files live (``<doc>.<base_id>.vsnap``, its edits since
beside it), and opening a document's base from one, or from the store when it is missing or
corrupt (``SnapshotFiles``). The file's format is ``snapformat``'s, what a base keeps in one
``basefile``'s; their public names are importable from here too.
"""

from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path
from typing import Any

from spatial import MemoryBudget

from .basefile import IMPORT_BYTES, import_budget, load, save, write_base
from .blocks import SnapshotCorrupt
from .errors import FULL_DISK
from .frames import CACHE_BYTES, DecodedFrames
from .snapformat import FORMAT, SnapshotFileError, SnapshotFileMissing, Writer, read
from .snapshots import Snapshot, build, new_base_id
from .stores import Store
from .table import ItemTable

__all__ = [
    "FORMAT",
    "IMPORT_BYTES",
    "SnapshotFileError",
    "SnapshotFileMissing",
    "SnapshotFiles",
    "Writer",
    "import_budget",
    "load",
    "read",
    "save",
    "write_base",
]

log = logging.getLogger("vantage.import")
SWEEP_GRACE_SECONDS = 3600.0  # a snapshot file of no current base younger than this is left alone

_KINDS = ("vsnap", "vedits")  # a base's file, and its edits' (``editfile``)


class SnapshotFiles:
    """Where snapshot files live (``<doc>.<base_id>.vsnap``, and the edits since beside them:
    ``.vedits``), and opening a document from one. Imports and compactions building into
    them aim to hold at most ``import_bytes`` at their peak (``import_budget``); the documents
    opened from them keep at most ``frames_bytes`` of their items decoded, together."""

    def __init__(
        self, directory: Path, import_bytes: int | None = None, frames_bytes: int = CACHE_BYTES
    ) -> None:
        self.directory = directory
        self.import_bytes = IMPORT_BYTES if import_bytes is None else import_bytes
        self.decoded = DecodedFrames(frames_bytes)
        self.rebuilt = 0  # files found stale or corrupt, and built again from the store

    def budget(self, items: int) -> MemoryBudget:
        """What a build of ``items`` into these files holds (``import_budget``)."""
        return import_budget(items, self.import_bytes)

    def path(self, doc_id: str, base_id: str) -> Path:
        return self.directory / f"{doc_id}.{base_id}.vsnap"

    def edits_path(self, doc_id: str, base_id: str) -> Path:
        """Where the edits since base ``base_id`` are saved (``editfile``)."""
        return self.directory / f"{doc_id}.{base_id}.vedits"

    def write(
        self, doc_id: str, table: ItemTable, version: int, base_id: str, full_disk_raises: bool = False
    ) -> bool:
        """Build the base of ``table`` into its file (``write_base``); False (logged) if it could
        not be written: it is a cache, the store is the truth (build it in memory then). With
        ``full_disk_raises`` (an import's or a compaction's new base), a full disk is raised:
        the store on it is full too, and an import is refused as the store refuses it.

        :raises OSError: ``ENOSPC`` or ``EDQUOT``, with ``full_disk_raises`` (no file left)
        """
        try:
            write_base(table, self.path(doc_id, base_id), version, base_id, self.budget(len(table)))
            return True
        except OSError as error:
            if full_disk_raises and error.errno in FULL_DISK:
                raise
            log.warning("could not write the snapshot file of %s: %s", doc_id, error)
            return False

    def base(
        self, store: Store, meta: dict[str, Any], name: bool = True, corrupt: str | None = None
    ) -> Snapshot:
        """The snapshot of the document's base (no edits): mapped from its file, else built
        from the store and saved, then mapped. A base without a name gets one first (``meta``
        is updated with it), unless not ``name``: inside a write, which replaces it anyway.
        ``corrupt``: why its file (found corrupt as it was read) is built again, not mapped."""
        doc_id, base_id, version = meta["id"], meta["base_id"], meta["base_version"]
        if corrupt is not None:
            log.warning("snapshot of %s rebuilt from the store: %s", doc_id, corrupt)
            self.rebuilt += 1
            self.remove(doc_id, base_id)
        elif base_id is not None:
            try:
                return load(self.path(doc_id, base_id), base_id, version, self.decoded)
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
        if self.write(doc_id, table, version, base_id):
            with contextlib.suppress(SnapshotFileError):
                return load(self.path(doc_id, base_id), base_id, version, self.decoded)
        return build(table, version, base_id)

    def check(self, store: Store) -> list[str]:
        """Check every block of each document's file (``vantage check``); a line about each.
        A corrupt file is removed, so the next open builds it again from the store."""
        said = []
        for meta in store.documents():
            doc_id, base_id, name = meta["id"], meta["base_id"], meta["name"]
            path = self.path(doc_id, base_id) if base_id is not None else None
            if path is None or not path.exists():
                said.append(f"{doc_id} {name!r}: no snapshot file yet (one is built at its next open)")
                continue
            try:
                _, _, size, blocks = read(path)
                blocks.check_all()
            except SnapshotFileMissing:  # removed meanwhile: a new base replaced it
                said.append(f"{doc_id} {name!r}: its file was replaced while it was checked")
            except (SnapshotFileError, SnapshotCorrupt) as error:
                path.unlink(missing_ok=True)
                why = blocks.bad if isinstance(error, SnapshotCorrupt) else str(error)
                said.append(
                    f"{doc_id} {name!r}: corrupt, {why}; removed (rebuilt from the store at its next open)"
                )
            else:
                said.append(f"{doc_id} {name!r}: {path.name} sound, {size / 2**20:,.1f} MiB checked")
        return said

    def sweep(self, store: Store, grace: float = SWEEP_GRACE_SECONDS) -> int:
        """Remove the files of no document's current base, snapshot or saved edits (a process
        killed mid-import left them, or one that wrote its file but not its base, or one that
        saved edits while a compaction replaced their base), and half-written ``.tmp`` files,
        older than ``grace`` seconds: a younger one may be an import's about to commit. The
        number removed."""
        current = {f"{d['id']}.{d['base_id']}.{kind}" for d in store.documents() for kind in _KINDS}
        cutoff, removed = time.time() - grace, 0
        for path in [
            *(p for kind in _KINDS for p in self.directory.glob(f"*.{kind}")),
            *self.directory.glob(".*.tmp"),
        ]:
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
        for kind in _KINDS:
            for path in self.directory.glob(f"{doc_id}.{base_id or '*'}.{kind}"):
                path.unlink(missing_ok=True)
