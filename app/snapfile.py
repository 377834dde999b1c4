"""Snapshot files: a document's built index and packed items in one file, mapped, not rebuilt;
where they live, and opening a document's base from one (or from the store when it is missing).

Layout (little-endian)::

    header: magic "VANTSNAP"  u32 format  u32 directory length
            u64 xxh3-64 of the directory and top sums  u64 where the directory is
    the arrays, from the first block boundary, each starting on a 64-byte boundary (a node
        record stays one cache line)
    block sums, on a block boundary: u64 xxh3-64 of each block of the arrays (see ``blocks``)
    directory: JSON {"meta": {...}, "arrays": {name: [dtype, shape, offset]}, "size": bytes}
        (two names may share an offset: one array written once)
    top sums: u64 xxh3-64 of each page of block sums

The arrays come first so that each is written as it is made and let go (``Writer``): an
import builds its base straight into its file a part at a time (``write_base``), never
holding it whole. A file is written to a temporary name, flushed to disk and renamed, so a
reader sees a whole file or none. ``read`` checks the header, the directory and the top sums, and maps the rest
read-only: each block is checked against its sum the first time it is read (``Blocks``), so
an open costs the same for any size of file. Every worker process that maps the same file
shares its pages through the page cache, so N workers hold about one copy.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import mmap
import os
import struct
import time
from collections.abc import Callable, Iterator, Mapping
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import xxhash

from spatial import QuadTree, runs
from spatial._kernels import index_type
from spatial._paging import in_steps, mapping
from spatial.overview import Overview

from .blocks import BLOCK, SUMS_PAGE, Blocks, BlockSums, SnapshotCorrupt, top_sums
from .errors import FULL_DISK
from .frames import Framed, framed_arrays, places_in, taken
from .heap import return_freed_memory
from .looks import Looks
from .snapshots import Snapshot, build, new_base_id
from .stores import Store
from .table import STEP_BYTES, ItemTable, Packed, high_halves, release, scratch_array, spilled_arrays
from .text import TextIndex

__all__ = [
    "FORMAT",
    "SnapshotFileError",
    "SnapshotFileMissing",
    "SnapshotFiles",
    "Writer",
    "load",
    "read",
    "save",
    "write_base",
]

log = logging.getLogger("vantage.import")
SWEEP_GRACE_SECONDS = 3600.0  # a snapshot file of no current base younger than this is left alone

FORMAT = 6  # 2: the text index for search; 3: blocks checked on first read; 4: items in the tree's
# order, their bodies compressed by frame; 5: each box and slot kept once, homes in one int32;
# 6: the directory after the arrays, so each is written as it is made
_MAGIC = b"VANTSNAP"
_HEADER = struct.Struct("<8sIIQQ")  # magic, format, directory length, checksum, where the directory is
_START = BLOCK  # where the arrays begin: the first block after the header
_ALIGN = 64


def _writeback() -> Callable[[int, int, int], None]:
    """``start(fd, offset, length)``: Linux's ``sync_file_range`` asked to start writing those
    bytes to the disk and not to wait; elsewhere nothing (the ``fsync`` at the end does it all)."""
    try:
        call = ctypes.CDLL(None, use_errno=True).sync_file_range
    except (AttributeError, OSError):
        return lambda fd, offset, length: None
    call.argtypes = (ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint)

    def start(fd: int, offset: int, length: int) -> None:
        call(fd, offset, length, _SYNC_FILE_RANGE_WRITE)  # failing, it leaves the fsync more to do

    return start


_SYNC_FILE_RANGE_WRITE = 2
# A file's bytes are pushed to the disk as it is written, every PUSH_BYTES: the fsync that
# ends it then waits for the last of them only (2.8 s of a 10M board's import waited for all)
PUSH_BYTES = 64 << 20
_start_writeback = _writeback()


class SnapshotFileError(Exception):
    """A snapshot file that cannot be used: missing, unreadable, of another format, or corrupt."""


class SnapshotFileMissing(SnapshotFileError):
    """No snapshot file there: never written here (a replica's first open), or removed."""


class Writer:
    """A snapshot file being written, an array at a time: each is written as it comes (and can
    be let go then), the sums of its blocks as they go by; ``finish`` writes the sums, the
    directory and, last, the header, then names the file. Until then it has a temporary name,
    removed if the writing stops short (a full disk, an error in what it was given)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        path.parent.mkdir(parents=True, exist_ok=True)
        self._out = open(self._temporary, "wb")  # noqa: SIM115 - closed by ``__exit__``
        self._out.seek(_START)  # the header, once the directory is known
        self._sums = BlockSums()
        self._directory: dict[str, list] = {}
        self._size = 0  # bytes of arrays written
        self._pushed = 0  # ... of which the disk was told to start writing (``_start_writeback``)
        self._done = False

    def __enter__(self) -> Writer:
        return self

    def __exit__(self, *_: object) -> None:
        self._out.close()
        if not self._done:
            self._temporary.unlink(missing_ok=True)

    def add(self, name: str, array: np.ndarray) -> None:
        """Write ``array`` as ``name``: done with it once this returns."""
        self._align()
        self._directory[name] = [array.dtype.str, list(array.shape), self._size]
        for piece in _pieces(array):
            self._put(piece)

    def same(self, name: str, first: str) -> None:
        """``name`` is the array written as ``first``: kept once."""
        self._directory[name] = self._directory[first]

    @contextlib.contextmanager
    def appending(self, name: str, dtype: str = "|u1", columns: int = 0) -> Iterator[Appended]:
        """Bytes written to what this yields, as they are made, are the array ``name`` of
        ``dtype``, of ``columns`` a row (0: one dimension)."""
        self._align()
        appended = Appended(self._put)
        at = self._size
        yield appended
        count = (self._size - at) // np.dtype(dtype).itemsize
        shape = [count // columns, columns] if columns else [count]
        self._directory[name] = [dtype, shape, at]

    def finish(self, meta: Mapping[str, Any]) -> int:
        """Write the sums, the directory (with ``meta``, JSON-able) and the header, flush it to
        disk and name it: the file's size."""
        sums = self._sums.sums()
        top = top_sums(sums).tobytes()
        sums_at = _sums_at(self._size)
        head = json.dumps({"meta": dict(meta), "arrays": self._directory, "size": self._size}).encode()
        self._out.seek(sums_at)
        self._out.write(sums.tobytes())
        tail = sums_at + sums.nbytes
        self._out.write(head + top)
        self._out.seek(0)
        checksum = xxhash.xxh3_64_intdigest(head + top)
        self._out.write(_HEADER.pack(_MAGIC, FORMAT, len(head), checksum, tail))
        self._out.flush()
        os.fsync(self._out.fileno())
        self._out.close()
        os.replace(self._temporary, self.path)
        self._done = True
        return tail + len(head) + len(top)

    def _align(self) -> None:
        if pad := _rounded(self._size, _ALIGN) - self._size:
            self._put(bytes(pad))

    def _put(self, data: bytes | memoryview) -> None:
        self._sums.update(data)
        self._out.write(data)
        self._size += len(data)
        if self._size - self._pushed >= PUSH_BYTES:
            self._out.flush()
            _start_writeback(self._out.fileno(), _START + self._pushed, self._size - self._pushed)
            self._pushed = self._size


class Appended:
    """An array of a file being written whose bytes are appended as they are made."""

    def __init__(self, put: Callable[[bytes | memoryview], None]) -> None:
        self._put = put
        self.size = 0  # bytes appended

    def write(self, data: bytes | memoryview) -> None:
        self._put(data)
        self.size += len(data)


def _add(out: Writer, arrays: Mapping[str, np.ndarray]) -> None:
    """Write each of ``arrays``: one given under two names (the same object) once."""
    first: dict[int, str] = {}  # the arrays are all held meanwhile: no id is reused
    for name, array in arrays.items():
        if (written := first.setdefault(id(array), name)) != name:
            out.same(name, written)
        else:
            out.add(name, array)


def _append(out: Appended, array: np.ndarray) -> None:
    """The bytes of ``array`` appended to ``out``, a step at a time."""
    for piece in _pieces(array):
        out.write(piece)


def _add_made(out: Writer, name: str, rows: np.ndarray, make: Callable[[np.ndarray], np.ndarray]) -> None:
    """Write ``make(rows)`` (one value a row) as ``name``, made a step of ``rows`` at a time
    (their pages handed back after each, mapped from a file): never held whole."""
    with out.appending(name, make(rows[:0]).dtype.str) as appended:
        for _, step in in_steps(rows):
            _append(appended, make(step))


def _taken(column: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``column[rows]``, the pages of ``column`` read at random handed back (mapped)."""
    taken = column[rows]
    release(column)
    return taken


def _pieces(array: np.ndarray) -> Iterator[memoryview]:
    """The bytes of ``array``, a step at a time."""
    flat = np.ascontiguousarray(array).reshape(-1).view(np.uint8)
    for step in range(0, len(flat), STEP_BYTES):
        yield flat[step : step + STEP_BYTES].data  # a memoryview of it
        release(array)  # one mapped from a file (a spilled import's) stays paged out


def _sums_at(size: int) -> int:
    """Where the block sums begin, after ``size`` bytes of arrays: on a block."""
    return _rounded(_START + size, BLOCK)


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
            magic, version, head_size, checksum, tail = _HEADER.unpack(
                source.read(_HEADER.size).ljust(_HEADER.size)
            )
            if magic != _MAGIC or version != FORMAT:
                raise SnapshotFileError(f"{path}: not a snapshot file of format {FORMAT}")
            source.seek(tail)
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
    sums_at, start = _sums_at(size), _START
    if len(mapped) < sums_at + 8 * blocks:
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


# What an import's build aims to hold at its peak (``VANTAGE_IMPORT_MEMORY_MB``): its runs are
# sized to what is left of it once the process's runtime (the interpreter, numpy, numba's
# compiled code: ~240 MB measured) and what the build holds whole (the tree's nodes and their
# ranges, a band's rows: ~5-7 bytes an item at 1e8 items) are counted
_IMPORT_BYTES = 1400 << 20
RUNTIME_BYTES = 256 << 20
WHOLE_BYTES_PER_ITEM = 7


def hold_imports_to(nbytes: int) -> None:
    """Imports in this process aim to hold at most ``nbytes`` at their peak."""
    global _IMPORT_BYTES
    _IMPORT_BYTES = nbytes


def size_runs(items: int) -> None:
    """Size the runs of a build of ``items`` to the import's aim (``hold_imports_to``): half
    of what is left of it, between ``runs.LEAST_RUN_BYTES`` and ``MOST_RUN_BYTES``. Past
    what the document needs at the least, it still imports, with runs at their least."""
    left = (_IMPORT_BYTES - RUNTIME_BYTES - WHOLE_BYTES_PER_ITEM * items) // 2
    if left < runs.LEAST_RUN_BYTES:
        least = RUNTIME_BYTES + WHOLE_BYTES_PER_ITEM * items + 2 * runs.LEAST_RUN_BYTES
        log.warning(
            "an import of %d items holds ~%d MB at the least, past the %d MB it aims at "
            "(VANTAGE_IMPORT_MEMORY_MB): its runs are at their least",
            items,
            least >> 20,
            _IMPORT_BYTES >> 20,
        )
    runs.hold(left)


def write_base(table: ItemTable, path: Path, version: int, base_id: str) -> int:
    """Build the base of ``table`` at ``version`` straight into a snapshot file at ``path``
    (``build`` builds one in memory): each part (the overview, the tree, the text) is built,
    written, and let go before the next, so the whole base is never held at once; their
    runs sized to the import's aim (``hold_imports_to``). The file's size."""
    size_runs(len(table))
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
            parts = tree(partial(_append, boxes))
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


_KINDS = ("vsnap", "vedits")  # a base's file, and its edits' (``editfile``)


class SnapshotFiles:
    """Where snapshot files live (``<doc>.<base_id>.vsnap``, and the edits since beside them:
    ``.vedits``), and opening a document from one."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.rebuilt = 0  # files found stale or corrupt, and built again from the store

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
            write_base(table, self.path(doc_id, base_id), version, base_id)
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
        if self.write(doc_id, table, version, base_id):
            with contextlib.suppress(SnapshotFileError):
                return load(self.path(doc_id, base_id), base_id, version)
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
