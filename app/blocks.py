"""A snapshot file's blocks, each checked against its checksum the first time it is read, so
that opening a file reads a few kilobytes, not the whole file, and no answer is built from a
corrupt byte.

The arrays of a file are cut into blocks of ``BLOCK`` bytes (a page: a query reads scattered
items, and checks about as many bytes as it reads), each with an xxh3-64 sum. The sums lie in
the file too, a page of them (``SUMS_PAGE`` sums) covered by one sum of the top level, which
the header's checksum covers: an open reads the header, the directory and the top sums.

Compiled code reports what it reads (``spatial.ReadWatch``): it marks the blocks it read that
are not checked yet, and the caller settles them before the answer leaves. Python code checks
whole arrays before reading them (``check``).
"""

from __future__ import annotations

import logging
import mmap
import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import xxhash

from spatial.kernels import READ_RUN

from .errors import Unavailable

__all__ = ["BLOCK", "BlockSums", "Blocks", "SUMS_PAGE", "SnapshotCorrupt", "top_sums"]

log = logging.getLogger("vantage.snapshots")
SHIFT = 12
BLOCK = 1 << SHIFT  # bytes a block
SUMS_PAGE = BLOCK // 8  # block sums a page of sums, under one top sum
BULK = 4096  # blocks checked between handing their pages back, when a whole array is checked
_NONE = np.empty(0, np.int64)
UNREAD, CHECKED, READ, BAD = 0, 1, 2, 3  # a block's mark (READ: or-ed in by compiled code)


class SnapshotCorrupt(Unavailable):
    """A block of a document's snapshot file does not match its checksum: the answer is not
    given, and the document is rebuilt from the store before the next one."""

    retry_after = 1


class BlockSums:
    """xxh3-64 of each ``BLOCK`` bytes of what is passed to ``update``, in order (the last
    block short): the sums of a file's arrays, made as they are written."""

    def __init__(self) -> None:
        self._sums: list[int] = []
        self._carry = bytearray()

    def update(self, data: bytes | memoryview) -> None:
        view = memoryview(data).cast("B")
        if self._carry:
            take = min(len(view), BLOCK - len(self._carry))
            self._carry += view[:take]
            view = view[take:]
            if len(self._carry) < BLOCK:
                return
            self._sums.append(xxhash.xxh3_64_intdigest(self._carry))
            self._carry.clear()
        whole = len(view) - len(view) % BLOCK
        self._sums.extend(xxhash.xxh3_64_intdigest(view[i : i + BLOCK]) for i in range(0, whole, BLOCK))
        self._carry += view[whole:]

    def sums(self) -> np.ndarray:
        if self._carry:
            self._sums.append(xxhash.xxh3_64_intdigest(self._carry))
            self._carry.clear()
        return np.array(self._sums, np.uint64)


def top_sums(sums: np.ndarray) -> np.ndarray:
    """xxh3-64 of each page of ``sums`` (``SUMS_PAGE`` of them, the last page short)."""
    raw = sums.view(np.uint8)
    page = SUMS_PAGE * 8
    return np.array(
        [xxhash.xxh3_64_intdigest(raw[i : i + page].data) for i in range(0, len(raw), page)], np.uint64
    )


class Blocks:
    """The blocks of the arrays region of a snapshot file (``mapped``; ``region``, at byte
    ``start`` of it), with their sums (``sums``, mapped: checked a page at a time against ``top``,
    read at open). ``names``: each array's ``(start, end, name)`` in the region."""

    def __init__(
        self,
        path: Path,
        mapped: mmap.mmap,
        start: int,
        region: np.ndarray,
        sums: np.ndarray,
        top: np.ndarray,
        names: Sequence[tuple[int, int, str]],
    ) -> None:
        self.path, self.start, self.names = path, start, names
        self._mapped = mapped
        self._region, self._sums, self._top = region, sums, top
        self.marks = np.zeros(len(sums), np.uint8)
        self.pending = np.zeros(2 + (len(sums) >> READ_RUN), np.int64)  # see spatial.ReadWatch
        self._pages = np.zeros(len(top), bool)
        self._base = region.ctypes.data
        self._sums_at = start + sums.ctypes.data - self._base  # where the sums lie in the file
        self._lock = threading.Lock()
        self.checked = 0  # bytes checked so far, sums included
        self.bad: str | None = None  # why the file is corrupt, once a bad block is found

    def places(self, arrays: Sequence[np.ndarray]) -> np.ndarray:
        """``shift``, then ``offset, row bytes`` of each array in the region."""
        out = [SHIFT]
        for array in arrays:
            if not array.nbytes:  # read nowhere (a tree's ids that are its slots)
                out += [0, 0]
                continue
            at = array.ctypes.data - self._base
            assert at >= 0 and at + array.nbytes <= len(self._region), "an array of this file's map"
            out += [at, array.strides[0] if array.ndim else array.itemsize]
        return np.array(out, np.int64)

    def settle(self) -> None:
        """Check the blocks compiled code marked read.

        :raises SnapshotCorrupt: if one is bad (or one was before)
        """
        self.pending[0] = 0
        read = []
        for run in np.flatnonzero(self.pending[1:]).tolist():  # only runs a read was flagged in
            self.pending[1 + run] = 0
            lo = run << READ_RUN
            read.append(np.flatnonzero(self.marks[lo : lo + (1 << READ_RUN)] >= READ) + lo)
        blocks = np.concatenate(read) if read else np.empty(0, np.int64)
        if len(blocks) > 1:  # a first read of many: from the disk at once, not a fault at a time
            self.prefetch(blocks)
        for block in blocks.tolist():
            self._check(block)

    def check(self, *arrays: np.ndarray) -> None:
        """Check every block of ``arrays`` (views into this file's map) not checked yet.

        :raises SnapshotCorrupt: if one is bad
        """
        todo = [blocks for array in arrays if len(blocks := self._unchecked(array))]
        if not todo:  # the common case: all checked already
            return
        every = np.concatenate(todo)
        for step in range(0, len(every), BULK):
            blocks = every[step : step + BULK]
            if len(blocks) > 1:  # from the disk at once: the file is mapped to read a page a fault
                self.prefetch(blocks)
            for block in blocks.tolist():
                self._check(block)
            if len(every) > BULK:  # whole arrays: their pages go back as they are checked
                lo, hi = int(blocks.min()), int(blocks.max()) + 1
                self._mapped.madvise(mmap.MADV_DONTNEED, self.start + (lo << SHIFT), (hi - lo) << SHIFT)

    def _unchecked(self, array: np.ndarray) -> np.ndarray:
        """The blocks of ``array`` not checked yet."""
        if not array.nbytes:
            return _NONE
        at = array.ctypes.data - self._base
        first, last = at >> SHIFT, (at + array.nbytes - 1) >> SHIFT
        if first == last:  # a row or a few (an edit's reads): no reduction, ~6x sooner
            return _NONE if self.marks[first] == CHECKED else np.array([first], np.int64)
        marks = self.marks[first : last + 1]
        if marks.min() == marks.max() == CHECKED:  # the common case: all checked already
            return _NONE
        return np.flatnonzero(marks != CHECKED) + first

    def prefetch(self, blocks: np.ndarray) -> None:
        """Ask the kernel to read ``blocks`` now, all at once, and the pages of sums that
        check them (a read that faults them in one by one waits for the disk each time); a
        no-op for those in memory already."""
        blocks = np.unique(blocks)
        runs = np.flatnonzero(np.diff(blocks, prepend=-2) != 1)  # where each run of blocks begins
        for lo, hi in zip(
            blocks[runs].tolist(), blocks[np.append(runs[1:], len(blocks)) - 1].tolist(), strict=True
        ):
            self._mapped.madvise(mmap.MADV_WILLNEED, self.start + (lo << SHIFT), (hi - lo + 1) << SHIFT)
        pages = np.unique(blocks // SUMS_PAGE)
        for page in pages[~self._pages[pages]].tolist():
            self._mapped.madvise(mmap.MADV_WILLNEED, self._sums_at + page * BLOCK, BLOCK)

    def release(self) -> None:
        """Hand back the pages of the file this process mapped (they stay in the page cache: a
        read maps them again). A scattered read maps the folio around its page, up to a few
        MB: a long run of them (an open catching up on 1,000 edits) held ~1 GB of a
        1e7-item file."""
        self._mapped.madvise(mmap.MADV_DONTNEED)

    def check_all(self) -> None:
        """Check every block of the file. :raises SnapshotCorrupt: if one is bad"""
        self.check(self._region)

    def _check(self, block: int) -> None:
        if self.marks[block] == CHECKED:
            return
        if self.marks[block] == BAD:
            raise SnapshotCorrupt(self._said(block))
        page = block // SUMS_PAGE
        if not self._pages[page]:
            sums = self._sums[page * SUMS_PAGE : (page + 1) * SUMS_PAGE]
            if xxhash.xxh3_64_intdigest(sums.view(np.uint8).data) != self._top[page]:
                first = page * SUMS_PAGE
                self._bad(block, f"the sums of blocks {first}-{first + len(sums) - 1}")
            self._pages[page] = True
            self.checked += sums.nbytes
        data = self._region[block << SHIFT : (block + 1) << SHIFT]
        if xxhash.xxh3_64_intdigest(data.data) != self._sums[block]:
            self._bad(block, f"block {block}")
        self.marks[block] = CHECKED
        self.checked += len(data)

    def _bad(self, block: int, what: str) -> None:
        self.marks[block] = BAD
        with self._lock:
            first = self.bad is None
            if first:
                self.bad = self._said(block, what)
        if first:  # once a file: the document is rebuilt from the store
            log.warning("%s", self.bad)
        raise SnapshotCorrupt(self._said(block))

    def _said(self, block: int, what: str | None = None) -> str:
        """What a client is told (``what`` None), or what the log says: the block and its arrays."""
        if what is None:
            return "the document's snapshot file is corrupt; it is being rebuilt from the store: try again"
        lo, hi = block << SHIFT, (block + 1) << SHIFT
        within = [name for start, end, name in self.names if start < hi and end > lo] or ["padding"]
        return f"{self.path}: {what} (for bytes {lo}-{hi} of the arrays: {', '.join(within)}) is corrupt"
