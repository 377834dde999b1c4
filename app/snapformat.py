"""The snapshot file format: named arrays in one file, each block of them checked against its
checksum the first time it is read, whatever the file's size. What a document's base keeps in
one: ``basefile``; where the files live: ``snapfile``.

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
import builds its base straight into its file a part at a time (``basefile.write_base``),
never holding it whole. A file is written to a temporary name, flushed to disk and renamed, so
a reader sees a whole file or none. ``read`` checks the header, the directory and the top
sums, and maps the rest read-only: each block is checked against its sum the first time it is
read (``Blocks``), so an open costs the same for any size of file. Every worker process that
maps the same file shares its pages through the page cache, so N workers hold about one copy.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import mmap
import os
import struct
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xxhash

from spatial.paging import STEP_BYTES, release

from .blocks import BLOCK, SUMS_PAGE, Blocks, BlockSums, top_sums

__all__ = ["Appended", "FORMAT", "SnapshotFileError", "SnapshotFileMissing", "Writer", "read"]

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
        try:
            self._out.close()  # flushes what is buffered: on a full disk, that fails too
        finally:
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

    def add(self, array: np.ndarray) -> None:
        """The bytes of ``array`` appended, a step at a time."""
        for piece in _pieces(array):
            self.write(piece)


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
