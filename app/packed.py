"""Packed columns: many byte strings in one buffer (``Packed``), and the files with no name an
import's columns go to (``Spill``, ``scratch_array``) so that it holds none of them in memory.

An import's columns (its bodies, the bulk of its bytes, its ids and boxes, then its offsets
and id index) can go to a ``Spill``: a file with no name, mapped, that the kernel pages in and
out as it needs, and each pass over them hands back the pages it read, so an import of any
size holds none of them in memory but the pass's.

``ItemTable`` (``table``) keeps a document's ids and bodies packed; ``Framed`` (``frames``)
reads a snapshot file's bodies like a ``Packed``, and writes its frames through these.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numba
import numpy as np

from spatial import paging
from spatial.kernels import UNWATCHED, copy, mark_read
from spatial.paging import STEP_BYTES, in_steps, release, release_rows
from spatial.quadtree import ReadWatch

__all__ = [
    "InMemory",
    "Packed",
    "Spill",
    "end_arrays",
    "mark_rows",
    "offsets_in",
    "scratch_array",
    "scratch_in_files",
    "spilled_arrays",
    "take_items",
]


SCRATCH_IN_MEMORY = 1 << 16  # bytes under which a scratch array is made in memory, not a file
_ENDS: dict[tuple[bytes, bytes], tuple[np.ndarray, np.ndarray]] = {}  # a join's ends, as arrays


def end_arrays(ends: tuple[bytes, bytes]) -> tuple[np.ndarray, np.ndarray]:
    """``ends`` as the compiled joins take them: made once for the few a caller passes."""
    made = _ENDS.get(ends)
    if made is None:
        made = (np.frombuffer(ends[0], np.uint8), np.frombuffer(ends[1], np.uint8))
        if len(_ENDS) < 64:  # a few constants in practice; never unbounded
            _ENDS[ends] = made
    return made


class Spill:
    """Bytes written to a file with no name in ``directory``, then mapped read-only: its pages
    belong to the kernel's page cache, not to the process, and go back to disk under pressure.
    Nothing is left behind by a process killed at any point: the file never had a name. Used
    as a context manager: a pass that fails closes its file."""

    def __init__(self, directory: Path) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self._file = tempfile.TemporaryFile(dir=directory)  # noqa: SIM115 (closed on exit)
        self.size = 0

    def __enter__(self) -> Spill:
        return self

    def __exit__(self, *_: object) -> None:
        self._file.close()

    def write(self, data: bytes | memoryview) -> None:
        self._file.write(data)
        self.size += len(data)

    def mapped(self, writable: bool = False) -> bytes | memoryview:
        """The bytes written, mapped: the map keeps the file until it is unmapped. ``writable``:
        mapped copy-on-write (what is written stays in the process), for code that takes
        writable arrays only (numba compiles code of its own for read-only ones)."""
        self._file.flush()
        if not self.size:  # an empty file cannot be mapped
            return b""
        return memoryview(
            mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_COPY if writable else mmap.ACCESS_READ)
        )


class InMemory:
    """A ``Spill``'s interface over bytes kept in memory."""

    def __init__(self) -> None:
        self._parts: list[bytes] = []
        self.size = 0

    def __enter__(self) -> InMemory:
        return self

    def __exit__(self, *_: object) -> None:
        pass

    def write(self, data: bytes | memoryview) -> None:
        self._parts.append(bytes(data))
        self.size += len(data)

    def mapped(self) -> bytes:
        return b"".join(self._parts)


class Packed:
    """Many byte strings in one buffer, item ``i`` at ``buffer[offsets[i]:offsets[i + 1]]``
    (a memoryview for a snapshot mapped from its file: items are then memoryviews too, and
    the offsets int32 when they fit: arithmetic on them widens first)."""

    __slots__ = ("array", "buffer", "offsets", "places", "watch")

    def __init__(
        self, buffer: bytes | memoryview, offsets: np.ndarray, watch: ReadWatch | None = None
    ) -> None:
        self.buffer, self.offsets = buffer, offsets
        self.array = np.frombuffer(buffer, np.uint8)  # the buffer as compiled code reads it
        # With ``watch`` (mapped from a file), reads are reported to it, then checked.
        self.watch = watch
        self.places = watch.places([self.array, offsets]) if watch is not None else UNWATCHED[2]

    @classmethod
    def of(cls, parts: Sequence[bytes]) -> Packed:
        lengths = np.fromiter(map(len, parts), np.int64, len(parts))
        return cls(b"".join(parts), np.concatenate(([0], np.cumsum(lengths))))

    @classmethod
    def concat(cls, packs: Sequence[Packed]) -> Packed:
        for pack in packs:
            pack.read_all()
        starts = np.cumsum([0] + [len(p.buffer) for p in packs[:-1]])
        offsets = [packs[0].offsets[:1]] + [p.offsets[1:] + s for p, s in zip(packs, starts, strict=True)]
        return cls(b"".join(p.buffer for p in packs), np.concatenate(offsets))

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def release(self) -> None:
        """``release`` the pages of the buffer and the offsets mapped from a file (a ``Spill``'s)."""
        release(self.buffer)
        release(self.offsets)

    def steps(self, size: int | None = None) -> Iterator[tuple[int, int]]:
        """Ranges ``[lo, hi)`` of the items, in order, of about ``size`` bytes each (one item
        at least; None: ``STEP_BYTES``, as it is when called); the pages read are released
        after each: a pass over a spilled buffer holds one step of it at a time."""
        size = STEP_BYTES if size is None else size
        self.read_all()
        lo, most = 0, int(np.iinfo(self.offsets.dtype).max)
        while lo < len(self):
            # the bound in the offsets' own type: another (a Python int) would have numpy
            # convert all of them (int32: an import's ids') at each step, 0.4 s and 8 bytes an item
            bound = self.offsets.dtype.type(min(int(self.offsets[lo]) + size, most))
            hi = int(np.searchsorted(self.offsets, bound, side="right")) - 1
            hi = min(max(hi, lo + 1), len(self))
            yield lo, hi
            self.release()
            lo = hi

    def __getitem__(self, i: int) -> bytes | memoryview:
        if self.watch is None:
            return self.buffer[self.offsets[i] : self.offsets[i + 1]]
        self.watch.check(self.offsets[i : i + 2])
        start, stop = int(self.offsets[i]), int(self.offsets[i + 1])
        self.watch.check(self.array[start:stop])
        return self.buffer[start:stop]

    def read_all(self) -> None:
        """Before Python reads the buffer as a whole: every block of it checked."""
        if self.watch is not None:
            self.watch.check(self.array, self.offsets)

    def join(self, positions: np.ndarray, sep: bytes = b",", ends: tuple[bytes, bytes] = (b"", b"")) -> bytes:
        """The items at ``positions`` joined by ``sep`` (one byte), between ``ends``: one
        allocation and one compiled call, the whole answer's bytes (a viewport's ~100 kB)
        copied once on the way."""
        if not len(positions):
            return ends[0] + ends[1]
        head, tail = end_arrays(ends)
        watch = self.watch
        if watch is None:
            marks, pending = UNWATCHED[:2]
        else:  # the offsets say how much to copy from where: checked before they are used
            marks, pending = watch.marks, watch.pending
            if mark_rows(positions, marks, pending, self.places):
                watch.settle()
            unread = _unchecked(self.offsets, positions, marks, self.places)
            if len(unread):  # a first read: the disk fetches them at once, not a fault at a time
                watch.prefetch(unread)
        out = _join(self.array, self.offsets, positions, sep[0], head, tail, marks, pending, self.places)
        if watch is not None and pending[0]:
            watch.settle()
        return out.tobytes()

    def unpacked(self, spill: Path | None = None) -> Packed:
        """These items as one buffer (``Framed.unpacked``): they are already."""
        return self

    def take(self, order: np.ndarray, spill: Path | None = None) -> Packed:
        """The items at ``order`` (positions), in that order, in a buffer of their own (with
        ``spill``, a directory: in a ``Spill`` there, written a step at a time)."""
        self.read_all()
        if spill is None:
            buffer, offsets = take_items(self.array, self.offsets, order)
            return Packed(buffer.tobytes(), offsets)
        offsets = offsets_in(self.offsets, order)
        self.release()  # the offsets read at random (mapped: a spilled table's)
        ends = offsets[1:]
        with Spill(spill) as out:
            start = 0
            while start < len(order):  # a step of about STEP_BYTES at a time
                done = int(ends[start - 1]) if start else 0
                stop = max(start + 1, int(np.searchsorted(ends, done + STEP_BYTES, side="right")))
                out.write(take_items(self.array, self.offsets, order[start:stop])[0].data)
                self.release()
                start = stop
            return Packed(out.mapped(), offsets)

    def spliced(self, at: dict[int, bytes], tail: Sequence[bytes] = (), spill: Path | None = None) -> Packed:
        """These items with those at the positions of ``at`` replaced by its items, then the
        items of ``tail``: copied a run at a time (with ``spill``, a directory: into a ``Spill``
        there, the pages read released after each step)."""
        self.read_all()
        offsets = _spliced_offsets(self.offsets, {p: len(item) for p, item in at.items()}, tail, spill)
        with Spill(spill) if spill is not None else InMemory() as out:
            start = 0
            for pos in [*sorted(at), len(self)]:  # the run before each replaced item, then the item
                self._copy(int(self.offsets[start]), int(self.offsets[pos]), out)
                if pos < len(self):
                    out.write(at[pos])
                start = pos + 1
            for item in tail:
                out.write(item)
            return Packed(out.mapped(), offsets)

    @classmethod
    def gather(
        cls, packs: Sequence[Packed], keeps: Sequence[np.ndarray], spill: Path | None = None
    ) -> Packed:
        """The items of each pack where its boolean mask is set, in order, copied a run at a
        time into one buffer (with ``spill``, a directory: into a ``Spill`` there): no
        intermediate copy of any pack."""
        offsets, runs, size = [np.zeros(1, np.int64)], [], 0
        for pack, keep in zip(packs, keeps, strict=True):
            pack.read_all()
            edges = np.flatnonzero(np.diff(np.concatenate(([False], keep, [False])).astype(np.int8)))
            for start, stop in edges.reshape(-1, 2).tolist():  # [start, stop) of each run of kept items
                lo, hi = int(pack.offsets[start]), int(pack.offsets[stop])
                runs.append((pack, lo, hi))
                offsets.append(pack.offsets[start + 1 : stop + 1].astype(np.int64) - lo + size)
                size += hi - lo
        if spill is None:
            return cls(b"".join(memoryview(p.buffer)[lo:hi] for p, lo, hi in runs), np.concatenate(offsets))
        with Spill(spill) as out:
            for pack, lo, hi in runs:
                pack._copy(lo, hi, out)
            return cls(out.mapped(), np.concatenate(offsets))

    def _copy(self, lo: int, hi: int, out: Spill | InMemory) -> None:
        """Bytes ``[lo, hi)`` of the buffer to ``out``, a step at a time, each step's pages
        handed back once read (when it is mapped)."""
        for step in range(lo, hi, STEP_BYTES):
            out.write(memoryview(self.buffer)[step : min(step + STEP_BYTES, hi)])
            self.release()


def scratch_array(directory: Path, length: int, dtype: type[np.generic]) -> np.ndarray:
    """An array of ``length`` values, not filled in, in a file with no name in ``directory``,
    mapped shared: what is written to it goes to the page cache, and ``release`` hands its
    pages back with nothing lost. The file goes with the array's last view. Its room on the
    disk is taken at once: a full disk raises ``OSError`` (ENOSPC) here, where a write to a
    page of a sparse file would kill the process (SIGBUS). Under ``SCRATCH_IN_MEMORY`` bytes,
    in memory: a file would cost more than it saves (a 300-item import made 48 of them).

    :raises OSError: if the disk has no room for it
    """
    size = length * np.dtype(dtype).itemsize
    if not size or size < SCRATCH_IN_MEMORY:  # an empty file cannot be mapped either
        return np.empty(length, dtype)
    directory.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryFile(dir=directory) as file:
        os.posix_fallocate(file.fileno(), 0, size)
        return np.frombuffer(mmap.mmap(file.fileno(), size, access=mmap.ACCESS_WRITE), dtype)


@contextlib.contextmanager
def scratch_in_files() -> Iterator[None]:
    """Within it, every scratch array is a file, however small: a small build takes the paths
    a large one's arrays take (the warm-up compiles their kernels so; tests cover them so).
    Not for a server's requests: it sets a module's value, for every thread."""
    global SCRATCH_IN_MEMORY
    held, SCRATCH_IN_MEMORY = SCRATCH_IN_MEMORY, 0
    try:
        yield
    finally:
        SCRATCH_IN_MEMORY = held


def spilled_arrays(arrays: Sequence[np.ndarray], directory: Path, writable: bool = False) -> list[np.ndarray]:
    """``arrays`` written to one ``Spill`` in ``directory``, and mapped back from it (the same
    shapes and types, ``writable`` as ``Spill.mapped``), each on a cache line."""
    with Spill(directory) as spill:
        places = []
        for array in arrays:
            spill.write(bytes(-spill.size % 64))
            places.append(spill.size)
            spill.write(np.ascontiguousarray(array).reshape(-1).view(np.uint8).data)
        mapped = spill.mapped(writable)
    return [
        np.frombuffer(mapped, a.dtype, a.size, at).reshape(a.shape)
        for a, at in zip(arrays, places, strict=True)
    ]


def _spliced_offsets(
    offsets: np.ndarray, lengths: dict[int, int], tail: Sequence[bytes], spill: Path | None
) -> np.ndarray:
    """``offsets`` (int64) with the items at the positions of ``lengths`` given its lengths,
    then those of ``tail``'s items: a step at a time, each item moved by what the replaced
    before it grew (with ``spill``, a directory: in a file there, each step's pages handed
    back once written, where the lengths and the offsets made whole held 16 bytes an item,
    1.6 GB at 1e8)."""
    n = len(offsets) - 1
    where = np.array(sorted(lengths), np.int64)
    grown = np.cumsum(
        [0, *(lengths[p] - int(offsets[p + 1] - offsets[p]) for p in where.tolist())], dtype=np.int64
    )
    length = n + 1 + len(tail)
    out = np.empty(length, np.int64) if spill is None else scratch_array(spill, length, np.int64)
    for lo, step in in_steps(offsets):
        made = out[lo : lo + len(step)]
        made[:] = step + grown[np.searchsorted(where, np.arange(lo, lo + len(step)))]  # replaced before
        release_rows(made)
    out[n + 1 :] = out[n] + np.cumsum([len(t) for t in tail], dtype=np.int64)
    return out


@numba.njit(cache=True, nogil=True)
def take_items(
    array: np.ndarray, offsets: np.ndarray, order: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """``(buffer, offsets)`` of the items of a pack (``array``, ``offsets``) at ``order``
    (positions), in that order: a buffer of their own, int64 offsets."""
    # Each item's start kept as it is first read: the copy then reads ``offsets`` in order, not
    # at random again (a cache miss an item less: 1.3-2x faster); each item one ``memcpy``.
    new = np.empty(len(order) + 1, np.int64)
    starts = np.empty(len(order), offsets.dtype)
    new[0] = 0
    for i in range(len(order)):
        starts[i] = start = offsets[order[i]]
        new[i + 1] = new[i] + offsets[order[i] + 1] - start
    out = np.empty(new[-1], np.uint8)
    for i in range(len(order)):
        copy(out, new[i], array, starts[i], new[i + 1] - new[i])
    return out, new


def offsets_in(
    offsets: np.ndarray, order: np.ndarray, spill: Path | None = None, places: np.ndarray | None = None
) -> np.ndarray:
    """The offsets of the items at ``order`` put end to end in that order, in one pass (numpy's
    diff, take and cumsum would hold three more arrays the size of it). With ``spill``, a
    directory, and ``places`` (each position's place in ``order``, -1: not in it): made in a
    file there (``scratch_array``) a window of places at a time, each by a pass over the
    items in the order they lie (``offsets`` and ``places`` read a step at a time, handed
    back): ``offsets`` are never read at random (a step of ``order`` read most of their
    pages: 730 MB at 1e8 items), and a window (the budget's ``window_bytes``) is held."""
    length = len(order) + 1
    if spill is None or places is None:
        out = np.empty(length, np.int64)
        out[0] = 0
        _offsets_in(offsets, order, out)
        return out
    out = scratch_array(spill, length, np.int64)
    out[0], total = 0, 0
    for a, b in paging.windows(len(order), 8, in_file=True):
        lengths = np.zeros(b - a, np.int64)
        for lo, step in in_steps(places):
            read = offsets[lo : lo + len(step) + 1]
            _lengths_at(read, step, a, lengths)
            release_rows(read)
        np.cumsum(lengths, out=lengths)
        lengths += total
        total = int(lengths[-1])
        made = out[a + 1 : a + 1 + len(lengths)]
        made[:] = lengths
        release_rows(made)
    return out


@numba.njit(cache=True, nogil=True)
def _lengths_at(
    offsets: np.ndarray, places: np.ndarray, a: int, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    # Each item (of a step: ``offsets`` theirs and the next's) placed in ``a..a + len(out)``:
    # its length at its place in ``out``
    for i in range(len(places)):
        p = places[i] - a
        if 0 <= p < len(out):
            out[p] = offsets[i + 1] - offsets[i]


@numba.njit(cache=True, nogil=True)
def _offsets_in(
    offsets: np.ndarray, order: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    # ``out[0]`` given: each next one the one before plus the item's length
    for i in range(len(order)):
        out[i + 1] = out[i] + offsets[order[i] + 1] - offsets[order[i]]


@numba.njit(cache=True, nogil=True)
def mark_rows(
    positions: np.ndarray, marks: np.ndarray, pending: np.ndarray, places: np.ndarray
) -> int:  # pragma: no cover - compiled
    """Report the offsets of the items at ``positions`` read (see ``ReadWatch``); how many
    of their blocks are not checked yet."""
    unchecked = 0
    for p in positions:
        unchecked += mark_read(marks, pending, places, 1, p, p + 2)
    return unchecked


@numba.njit(cache=True, nogil=True)
def _unchecked(
    offsets: np.ndarray, positions: np.ndarray, marks: np.ndarray, places: np.ndarray
) -> np.ndarray:  # pragma: no cover - compiled
    """The blocks of the items at ``positions`` not checked yet (see ``ReadWatch``), each once
    when they come in order."""
    shift, at = places[0], places[1]
    out = np.empty(len(positions) + 1, np.int64)
    k = 0
    for p in positions:
        for b in range((at + offsets[p]) >> shift, ((at + offsets[p + 1] - 1) >> shift) + 1):
            if marks[b] == 0 and (k == 0 or out[k - 1] != b):
                if k == len(out):
                    grown = np.empty(2 * len(out), np.int64)
                    grown[:k] = out
                    out = grown
                out[k] = b
                k += 1
    return out[:k]


@numba.njit(cache=True, nogil=True)
def _join(
    buffer: np.ndarray,
    offsets: np.ndarray,
    positions: np.ndarray,
    sep: int,
    head: np.ndarray,
    tail: np.ndarray,
    marks: np.ndarray,
    pending: np.ndarray,
    places: np.ndarray,
) -> np.ndarray:  # pragma: no cover
    size = len(head) + len(positions) - 1 + len(tail)
    for p in positions:
        mark_read(marks, pending, places, 0, offsets[p], offsets[p + 1])
        size += offsets[p + 1] - offsets[p]
    out = np.empty(size, np.uint8)
    copy(out, 0, head, 0, len(head))
    k = len(head)
    for i in range(len(positions)):
        if i:
            out[k] = sep
            k += 1
        start, stop = offsets[positions[i]], offsets[positions[i] + 1]
        copy(out, k, buffer, start, stop - start)
        k += stop - start
    copy(out, k, tail, 0, len(tail))
    return out
