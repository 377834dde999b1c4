"""Snapshot files: a document's built index and packed items in one file, mapped, not rebuilt;
where they live, and opening a document's base from one (or from the store when it is missing).

Layout (little-endian)::

    magic "VANTSNAP"  u32 format  u32 directory length  u64 xxh3-64 of the directory and top sums
    directory: JSON {"meta": {...}, "arrays": {name: [dtype, shape, offset]}, "size": bytes}
        (two names may share an offset: one array written once)
    top sums: u64 xxh3-64 of each page of block sums
    block sums, on a block boundary: u64 xxh3-64 of each block of the arrays (see ``blocks``)
    the arrays, on a block boundary, each starting on a 64-byte boundary (a node record stays
    one cache line)

A file is written to a temporary name, flushed to disk and renamed, so a reader sees a whole
file or none. ``read`` checks the header, the directory and the top sums, and maps the rest
read-only: each block is checked against its sum the first time it is read (``Blocks``), so
an open costs the same for any size of file. Every worker process that maps the same file
shares its pages through the page cache, so N workers hold about one copy.
"""

from __future__ import annotations

import contextlib
import json
import logging
import mmap
import os
import struct
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xxhash

from spatial import QuadTree
from spatial.overview import Overview

from .blocks import BLOCK, SUMS_PAGE, Blocks, BlockSums, SnapshotCorrupt, top_sums
from .frames import Framed
from .looks import Looks
from .snapshots import Later, Snapshot, build, new_base_id, snapshot_arrays
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

FORMAT = 5  # 2: the text index for search; 3: blocks checked on first read; 4: items in the tree's
# order, their bodies compressed by frame; 5: each box and slot kept once, homes in one int32
_MAGIC = b"VANTSNAP"
_HEADER = struct.Struct("<8sIIQ")  # magic, format, directory length, checksum
_ALIGN = 64


class SnapshotFileError(Exception):
    """A snapshot file that cannot be used: missing, unreadable, of another format, or corrupt."""


class SnapshotFileMissing(SnapshotFileError):
    """No snapshot file there: never written here (a replica's first open), or removed."""


def write(path: Path, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray | Later]) -> int:
    """Write ``arrays`` and ``meta`` (JSON-able) to ``path`` atomically, with the sums of its
    blocks; the file's size. Streamed: no second copy of the arrays is made, and each ``Later``
    is made as its turn comes, then let go. An array given under two names (the same object)
    is written once."""
    directory: dict[str, list] = {}
    written: dict[int, str] = {}  # id of each array written: its first name
    size = 0
    for name, array in arrays.items():
        if (first := written.get(id(array))) is not None:
            directory[name] = directory[first]
            continue
        written[id(array)] = name
        size = _rounded(size, _ALIGN)
        directory[name] = [np.dtype(array.dtype).str, list(array.shape), size]
        size += array.nbytes
    head = json.dumps({"meta": dict(meta), "arrays": directory, "size": size}).encode()
    sums_at, start = _layout(len(head), size)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(temporary, "wb") as out:
            summer = BlockSums()
            out.seek(start)  # the header and the sums, once they are known
            at = 0
            for name, array in arrays.items():
                if written[id(array)] != name:
                    continue
                made = array.make() if isinstance(array, Later) else array
                assert made.dtype == array.dtype and made.shape == array.shape, name
                for piece in _pieces(bytes(directory[name][2] - at), made):
                    summer.update(piece)
                    out.write(piece)
                at = directory[name][2] + made.nbytes
                del made
            sums = summer.sums()
            top = top_sums(sums)
            out.seek(0)
            checksum = xxhash.xxh3_64_intdigest(head + top.tobytes())
            out.write(_HEADER.pack(_MAGIC, FORMAT, len(head), checksum) + head + top.tobytes())
            out.seek(sums_at)
            out.write(sums.tobytes())
            out.flush()
            os.fsync(out.fileno())
    except BaseException:  # a full disk, say: nothing half-written stays behind
        temporary.unlink(missing_ok=True)
        raise
    os.replace(temporary, path)
    return start + size


def _pieces(padding: bytes, array: np.ndarray) -> Iterator[bytes | memoryview]:
    """The bytes of ``array`` after ``padding``, a step at a time."""
    yield padding
    flat = np.ascontiguousarray(array).reshape(-1).view(np.uint8)
    for step in range(0, len(flat), STEP_BYTES):
        yield flat[step : step + STEP_BYTES].data  # a memoryview of it
        release(array)  # one mapped from a file (a spilled import's) stays paged out


def _layout(head: int, size: int) -> tuple[int, int]:
    """Where the block sums and the arrays begin, for a directory of ``head`` bytes and
    ``size`` bytes of arrays: after the header, the directory and the top sums, on blocks."""
    blocks = -(-size // BLOCK)
    sums_at = _rounded(_HEADER.size + head + 8 * -(-blocks // SUMS_PAGE), BLOCK)
    return sums_at, _rounded(sums_at + 8 * blocks, BLOCK)


def _rounded(offset: int, to: int) -> int:
    """``offset`` rounded up to a multiple of ``to``."""
    return -(-offset // to) * to


def read(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray], int, Blocks]:
    """``(meta, arrays, size, blocks)`` of the file at ``path``: read-only arrays over a shared
    map, and their blocks, each to be checked on its first read (see ``Blocks``). Reads the
    header, the directory and the top sums, a few kilobytes whatever the file's size.

    :raises SnapshotFileError: if the file is missing, short, of another format, or its header
        is corrupt
    """
    try:
        with open(path, "rb") as source:
            magic, version, head_size, checksum = _HEADER.unpack(
                source.read(_HEADER.size).ljust(_HEADER.size)
            )
            if magic != _MAGIC or version != FORMAT:
                raise SnapshotFileError(f"{path}: not a snapshot file of format {FORMAT}")
            raw_head = source.read(head_size)
            head = json.loads(raw_head)
            size = int(head["size"])
            blocks = -(-size // BLOCK)
            raw_top = source.read(8 * -(-blocks // SUMS_PAGE))
            if xxhash.xxh3_64_intdigest(raw_head + raw_top) != checksum:
                raise SnapshotFileError(f"{path}: checksum mismatch in its header (the file is corrupt)")
            mapped = mmap.mmap(source.fileno(), 0, access=mmap.ACCESS_READ)
            # Reads are scattered: a fault reads its page, not the device's read-ahead around it
            # (8 MiB here: a first answer read ~130 MB for ~2 MB of blocks). What a read needs
            # is fetched at once (``Blocks.prefetch``), and whole arrays a step at a time.
            mapped.madvise(mmap.MADV_RANDOM)
    except FileNotFoundError:
        raise SnapshotFileMissing(f"{path}: no such file") from None
    except (OSError, ValueError, KeyError, TypeError) as error:  # ValueError: empty, or bad JSON
        raise SnapshotFileError(f"{path}: unreadable ({error})") from None
    sums_at, start = _layout(head_size, size)
    if len(mapped) < start + size:
        raise SnapshotFileError(f"{path}: {len(mapped)} bytes, shorter than its directory says")
    region = np.frombuffer(mapped, np.uint8, size, start)
    try:
        arrays, names = {}, []
        for name, (dtype, shape, offset) in head["arrays"].items():
            count = int(np.prod(shape)) if shape else 1
            arrays[name] = np.frombuffer(region, np.dtype(dtype), count, offset).reshape(shape)
            names.append((offset, offset + arrays[name].nbytes, name))
    except (ValueError, KeyError, TypeError) as error:  # a checksum collision, in effect
        raise SnapshotFileError(f"{path}: unreadable directory ({error})") from None
    sums = np.frombuffer(mapped, np.uint64, blocks, sums_at)
    top = np.frombuffer(raw_top, np.uint64)
    return head["meta"], arrays, len(mapped), Blocks(path, mapped, start, region, sums, top, names)


def save(snap: Snapshot, path: Path) -> int:
    """Write ``snap``'s base (no edits) to ``path`` as a snapshot file; its size."""
    assert not snap.edits and snap.base_id is not None, "only a fresh base is saved"
    assert snap.looks is not None and snap.overview is not None and snap.text is not None, "a built base"
    meta = {"version": snap.version, "base_id": snap.base_id, "kinds": list(snap.looks.names)}
    arrays = snapshot_arrays(snap.table, snap.tree, snap.overview, snap.text, path.parent)
    try:
        return write(path, meta, arrays)
    finally:
        release(arrays["bodies.frames"])  # made in a spill, read once


def load(path: Path, base_id: str, version: int) -> Snapshot:
    """The snapshot saved at ``path``, mapped, if it is the base ``base_id`` at ``version``;
    its blocks are checked as they are first read.

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
