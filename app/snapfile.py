"""Snapshot files: a document's built index and packed items in one file, mapped, not rebuilt;
where they live, and opening a document's base from one (or from the store when it is missing).

Layout (little-endian)::

    magic "VANTSNAP"  u32 format  u32 directory length  u64 xxh3-64 of everything after the header
    directory: JSON {"meta": {...}, "arrays": {name: [dtype, shape, offset]}}
    the arrays, each starting on a 64-byte boundary (a node record stays one cache line)

A file is written to a temporary name, flushed to disk and renamed, so a reader sees a whole
file or none. ``read`` maps it read-only and checks its header, format and checksum before
anything is used: every worker process that maps the same file shares its pages through the
page cache, so N workers hold about one copy.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import mmap
import os
import struct
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xxhash

from spatial import QuadTree
from spatial.overview import Overview

from .looks import Looks
from .snapshots import Snapshot, build, new_base_id, snapshot_arrays
from .stores import Store
from .table import STEP_BYTES, ItemTable, Packed, release
from .text import TextIndex

__all__ = [
    "FORMAT",
    "SnapshotFileError",
    "SnapshotFileMissing",
    "SnapshotFiles",
    "load",
    "read",
    "save",
    "write",
]

log = logging.getLogger("vantage.import")
SWEEP_GRACE_SECONDS = 3600.0  # a snapshot file of no current base younger than this is left alone

FORMAT = 2  # 2: the text index for search
_MAGIC = b"VANTSNAP"
_HEADER = struct.Struct("<8sIIQ")  # magic, format, directory length, checksum
_ALIGN = 64


class SnapshotFileError(Exception):
    """A snapshot file that cannot be used: missing, unreadable, of another format, or corrupt."""


class SnapshotFileMissing(SnapshotFileError):
    """No snapshot file there: never written here (a replica's first open), or removed."""


def write(path: Path, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> int:
    """Write ``arrays`` and ``meta`` (JSON-able) to ``path`` atomically; the file's size.
    Streamed: no second copy of the arrays is made."""
    directory: dict[str, list] = {}
    offset = 0
    for name, array in arrays.items():
        offset = _aligned(offset)
        directory[name] = [array.dtype.str, list(array.shape), offset]
        offset += array.nbytes
    head = json.dumps({"meta": dict(meta), "arrays": directory}).encode()
    start = _aligned(_HEADER.size + len(head))  # where the arrays begin
    hasher = xxhash.xxh3_64()
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(temporary, "wb") as out:

            def put(data: bytes | memoryview) -> None:
                hasher.update(data)
                out.write(data)

            out.write(bytes(_HEADER.size))  # the header, once the checksum is known
            put(head + bytes(start - _HEADER.size - len(head)))
            at = 0
            for name, array in arrays.items():
                put(bytes(directory[name][2] - at))
                flat = np.ascontiguousarray(array).reshape(-1).view(np.uint8)
                for step in range(0, len(flat), STEP_BYTES):
                    put(flat[step : step + STEP_BYTES].data)  # a memoryview of it
                    release(array)  # one mapped from a file (a spilled import's) stays paged out
                at = directory[name][2] + array.nbytes
            out.seek(0)
            out.write(_HEADER.pack(_MAGIC, FORMAT, len(head), hasher.intdigest()))
            out.flush()
            os.fsync(out.fileno())
    except BaseException:  # a full disk, say: nothing half-written stays behind
        temporary.unlink(missing_ok=True)
        raise
    os.replace(temporary, path)
    return start + offset


def _digest(source: io.BufferedReader, start: int) -> int:
    """xxh3-64 of the file from ``start``, read a step at a time through one buffer, not
    through the map: the pages stay the page cache's, not counted to the process."""
    hasher, buffer = xxhash.xxh3_64(), bytearray(STEP_BYTES)
    source.seek(start)
    while size := source.readinto(buffer):
        hasher.update(memoryview(buffer)[:size])
    return hasher.intdigest()


def _aligned(offset: int) -> int:
    return -(-offset // _ALIGN) * _ALIGN


def read(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray], int]:
    """``(meta, arrays, size)`` of the file at ``path``: read-only arrays over a shared map.

    :raises SnapshotFileError: if the file is missing, short, of another format or corrupt
    """
    try:
        with open(path, "rb") as source:
            mapped = mmap.mmap(source.fileno(), 0, access=mmap.ACCESS_READ)
            digest = _digest(source, _HEADER.size)
    except FileNotFoundError:
        raise SnapshotFileMissing(f"{path}: no such file") from None
    except (OSError, ValueError) as error:  # ValueError: an empty file cannot be mapped
        raise SnapshotFileError(f"{path}: {error}") from None
    if len(mapped) < _HEADER.size:
        raise SnapshotFileError(f"{path}: {len(mapped)} bytes, shorter than a header")
    magic, version, head_size, checksum = _HEADER.unpack_from(mapped)
    if magic != _MAGIC or version != FORMAT:
        raise SnapshotFileError(f"{path}: not a snapshot file of format {FORMAT}")
    raw = np.frombuffer(mapped, np.uint8)
    if digest != checksum:
        raise SnapshotFileError(f"{path}: checksum mismatch (the file is corrupt)")
    try:
        head = json.loads(bytes(raw[_HEADER.size : _HEADER.size + head_size]))
        start = _aligned(_HEADER.size + head_size)
        arrays = {}
        for name, (dtype, shape, offset) in head["arrays"].items():
            count = int(np.prod(shape)) if shape else 1
            arrays[name] = np.frombuffer(mapped, np.dtype(dtype), count, start + offset).reshape(shape)
    except (ValueError, KeyError, TypeError) as error:  # a checksum collision, in effect
        raise SnapshotFileError(f"{path}: unreadable directory ({error})") from None
    return head["meta"], arrays, len(mapped)


def save(snap: Snapshot, path: Path) -> int:
    """Write ``snap``'s base (no edits) to ``path`` as a snapshot file; its size."""
    assert not snap.edits and snap.base_id is not None, "only a fresh base is saved"
    assert snap.looks is not None and snap.overview is not None and snap.text is not None, "a built base"
    meta = {"version": snap.version, "base_id": snap.base_id, "kinds": list(snap.looks.names)}
    return write(path, meta, snapshot_arrays(snap.table, snap.tree, snap.overview, snap.text))


def load(path: Path, base_id: str, version: int) -> Snapshot:
    """The snapshot saved at ``path``, mapped, if it is the base ``base_id`` at ``version``.

    :raises SnapshotFileError: if the file is missing, corrupt, or of another base
    """
    meta, arrays, size = read(path)
    if meta.get("base_id") != base_id or meta.get("version") != version:
        raise SnapshotFileError(
            f"{path}: of base {meta.get('base_id')} at version {meta.get('version')}, not {base_id} at {version}"
        )
    try:
        table = ItemTable(
            Packed(arrays["ids.buffer"].data, arrays["ids.offsets"]),  # memoryviews of the map
            Packed(arrays["bodies.buffer"].data, arrays["bodies.offsets"]),
            arrays["boxes"],
        )
        table.__dict__["_index"] = (
            arrays["index.hashes"],
            arrays["index.order"],
        )  # the cached_property's slot
        tree = QuadTree.from_arrays(_under(arrays, "tree."))
        overview = Overview.from_arrays(_under(arrays, "overview."))
        text = TextIndex.from_arrays(_under(arrays, "text."))
    except (KeyError, ValueError) as error:
        raise SnapshotFileError(f"{path}: not a snapshot ({error})") from None
    names = tuple(meta["kinds"])
    looks = Looks(names, {n: k for k, n in enumerate(names)})
    return Snapshot.base_of(table, tree, overview, looks, text, version, base_id, size)


def _under(arrays: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
    return {k[len(prefix) :]: v for k, v in arrays.items() if k.startswith(prefix)}


class SnapshotFiles:
    """Where snapshot files live (``<doc>.<base_id>.vsnap``), and opening a document from one."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.rebuilt = 0  # files found stale or corrupt, and built again from the store

    def path(self, doc_id: str, base_id: str) -> Path:
        return self.directory / f"{doc_id}.{base_id}.vsnap"

    def save(self, doc_id: str, snap: Snapshot) -> bool:
        """Write ``snap``'s file; False (logged) if it could not be: it is a cache, the store is the truth."""
        assert snap.base_id is not None, "only a base is saved"
        try:
            save(snap, self.path(doc_id, snap.base_id))
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
                return load(self.path(doc_id, base_id), base_id, version)
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
            return load(self.path(doc_id, base_id), base_id, version)
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
