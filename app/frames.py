"""Item bodies compressed a frame at a time: how a snapshot file keeps them (~3x smaller).

A file lays its items out in the tree's order (see ``basefile.write_base``), so the
items of one screen lie in a few consecutive frames of ``FRAME_BYTES`` (cut between items):
an answer decompresses those (~40 us a frame: ~0.6 ms for a screen of a board that none is
cached of), and a cache of the frames decoded last (a ``DecodedFrames``, shared by the
documents of a ``SnapshotFiles``) keeps panning from decoding them again. A pass over every item (an export, a merge) decompresses each frame
once, in order, into a ``Spill``.

Arrays: ``frames`` (the zstd frames end to end), ``at`` (where each begins, and the end),
``first`` (each frame's first item, and n) and ``offsets`` (each item's start in the bodies
as if decompressed end to end, and the end): item ``i`` of frame ``f`` begins at byte
``offsets[i] - offsets[first[f]]`` of that frame decompressed.
"""

from __future__ import annotations

import ctypes
import itertools
import mmap
import os
import sys
import tempfile
import threading
import weakref
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Protocol

import numba
import numpy as np
import zstandard

from spatial.kernels import UNWATCHED, copy, index_type
from spatial.paging import filled, placed, release, release_rows
from spatial.quadtree import ReadWatch

from .packed import InMemory, Packed, Spill, end_arrays, mark_rows, offsets_in, scratch_array, take_items

__all__ = ["DecodedFrames", "FRAME_BYTES", "Framed", "framed_arrays", "places_in", "taken"]

# 16 KiB: a 1M board's JSON from 130 to 44 B an item in the import's order, 39 in the tree's
# (64 KiB: 41 and 39, with 4x the bytes a screen decodes)
FRAME_BYTES = 1 << 14
CACHE_BYTES = 32 << 20  # decoded frames kept by default, all documents': ~2,000, ~100 screens
BUCKET_BYTES = 1 << 23  # bytes of items a bucket gathers, in memory, to put them in order (< 2 GiB)
PASS_BYTES = 1 << 22  # bytes of items a pass reads (or decodes) at a time
_NORESERVE = getattr(mmap, "MAP_NORESERVE", 0x4000 if sys.platform == "linux" else 0)  # virtual: no swap held
LEVEL = 1  # zstd's level: faster, and no larger than 3 on frames this small
# fallocate(2), to punch holes in a file: Linux's C library has it
_fallocate = ctypes.CDLL(None, use_errno=True).fallocate if sys.platform == "linux" else None
if _fallocate is not None:
    _fallocate.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]


def framed_arrays(
    bodies: Packed,
    order: np.ndarray,
    spill: Path | None = None,
    out: Sink | None = None,
    places: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The items of ``bodies`` at ``order`` (positions), in that order, cut into frames of about
    ``FRAME_BYTES`` (an item larger gets one of its own), each compressed: the arrays ``Framed``
    reads. With ``spill``, a directory, the items on their way go to files there, not to
    memory; so do the frames, unless ``out``: then they are written there as they are made (a
    snapshot file's array), not returned. ``places``: each position's place in ``order``
    (-1: not in it), if the caller holds it (else made when needed)."""
    bodies.read_all()
    if spill is not None and places is None:
        places = places_in(order, len(bodies), spill)
    offsets = offsets_in(bodies.offsets, order, spill, places)  # with ``spill``, in a file
    first = _cuts(offsets, FRAME_BYTES)
    compressor = zstandard.ZstdCompressor(level=LEVEL, write_checksum=False)
    at = np.zeros(len(first), np.int64)
    made = {"at": at, "first": first, "offsets": offsets}
    with Spill(spill) if spill is not None and out is None else InMemory() as kept, _Beside() as beside:
        sink = kept if out is None else out

        def frame(f: int, g: int, items: np.ndarray) -> None:
            for k, piece in enumerate(
                _compressed(compressor, items, offsets[first[f : g + 1]] - offsets[first[f]])
            ):
                sink.write(piece)
                at[f + k + 1] = sink.size

        # A bucket is compressed and written while the next is put in order
        for f, g, items in _in_order(bodies, order, offsets, first, spill, places):
            beside.then(frame, f, g, items)
        beside.wait()
        if out is None:
            made["frames"] = np.frombuffer(kept.mapped(), np.uint8)
    return made


def taken(items: Packed | Framed, order: np.ndarray, spill: Path, places: np.ndarray | None = None) -> Packed:
    """The items at ``order`` (positions), in that order, into a ``Spill`` in ``spill``, put in
    order through buckets (``_in_order``): ``items`` read in the order they lie, a step at a
    time, never a page of them at random (a mapped import's ids: each step of a take in
    ``order`` would read most of their pages). ``places``: ``framed_arrays``'."""
    items.read_all()  # mapped from a file: every block checked before its offsets are read
    if places is None:
        places = places_in(order, len(items), spill)
    offsets = offsets_in(items.offsets, order, spill, places)  # in a file too
    with Spill(spill) as out:
        for _, _, chunk in _in_order(items, order, offsets, None, spill, places):
            out.write(chunk.data)
        return Packed(out.mapped(), offsets)


class _Beside:
    """Steps run in order on a thread of their own, one at a time, while the caller makes the
    next: ``then`` waits for the step before (so at most two are held: the one running, the
    one being made) and raises what it raised."""

    def __init__(self) -> None:
        self._pool = ThreadPoolExecutor(1)
        self._last: Future[None] | None = None

    def __enter__(self) -> _Beside:
        return self

    def __exit__(self, *_: object) -> None:
        self._pool.shutdown(wait=True)

    def then(self, step: Callable[..., None], *args: object) -> None:
        self.wait()
        self._last = self._pool.submit(step, *args)

    def wait(self) -> None:
        if self._last is not None:
            last, self._last = self._last, None
            last.result()


class Sink(Protocol):
    """Where frames are written: ``size`` bytes so far."""

    size: int

    def write(self, data: bytes | memoryview) -> None: ...


def _compressed(
    compressor: zstandard.ZstdCompressor, items: np.ndarray, bounds: np.ndarray
) -> Iterator[bytes | memoryview]:
    """The frames of ``items`` cut at ``bounds``, compressed on every core (one at a time if
    any is empty: zstd's batch refuses those)."""
    lengths = np.diff(bounds)
    if not lengths.all():
        yield from (compressor.compress(items[lo:hi].data) for lo, hi in itertools.pairwise(bounds.tolist()))
        return
    segments = np.column_stack((bounds[:-1], lengths)).astype(np.uint64)
    frames = compressor.multi_compress_to_buffer(
        zstandard.BufferWithSegments(items.data, segments.tobytes()), threads=-1
    )
    # (a segment exposes the buffer protocol; zstandard's stubs do not say so)
    yield from (memoryview(frames[k]) for k in range(len(frames)))  # type: ignore[arg-type]


def _in_order(
    bodies: Packed | Framed,
    order: np.ndarray,
    offsets: np.ndarray,
    first: np.ndarray | None,
    spill: Path | None,
    places: np.ndarray | None = None,
) -> Iterator[tuple[int, int, np.ndarray]]:
    """``(f, g, items)``: the items of groups ``f`` to ``g`` (``order``'s, all of ``bodies``' or
    some; ``offsets`` theirs, ``first`` each group's first: frames, say; None: an item a
    group) end to end, a bucket of about ``BUCKET_BYTES`` at a time (``places``:
    ``framed_arrays``').

    Spilled or framed ``bodies`` are read in two passes in order, not one in ``order`` (a page
    touched, or a frame decoded, an item: slow, and pages counted against the process while
    mapped): each item is written where its bucket lies in a scratch file in ``spill``, in
    the order it comes, then each bucket is read back and put in order in memory. Both passes
    read their items in the order they lie and write each where it goes (``_to_buckets``,
    ``_from_bucket``): a random write costs less than a random read, which stalls. Items in
    memory are taken as they are."""
    group_at = _cuts(offsets if first is None else offsets[first], BUCKET_BYTES)  # each bucket's first group
    edges = group_at if first is None else first[group_at]  # ... and its first item
    release(offsets)  # (mapped, as ``offsets_in`` makes them with a spill: read where they lie)
    if isinstance(bodies, Packed) and (spill is None or not isinstance(bodies.buffer, memoryview)):
        for b in range(len(edges) - 1):
            items, _ = take_items(bodies.array, bodies.offsets, order[edges[b] : edges[b + 1]])
            yield int(group_at[b]), int(group_at[b + 1]), items
        return
    n = len(order)
    slot = places_in(order, len(bodies), spill) if places is None else places
    # Each bucket's places, in the order its items came: in a file, its pages handed back
    # after each chunk (with a spill: else 4 bytes an item held through both passes)
    arrived = np.empty(n, index_type(n)) if spill is None else scratch_array(spill, n, index_type(n))
    filled = edges[:-1].copy()  # how far each bucket's are in ``arrived``
    cursor = offsets[edges[:-1]].copy()  # where each bucket's next item goes
    # (a few reads, but each maps a folio of the file's pages around it: at 1e8 items, most
    # of the offsets' pages were held through the first pass)
    release(offsets)
    with tempfile.TemporaryFile(dir=spill) as scratch, _Beside() as beside:

        def write(items: np.ndarray, bounds: np.ndarray, sizes: np.ndarray, at: np.ndarray) -> None:
            for b in np.flatnonzero(sizes).tolist():
                os.pwrite(scratch.fileno(), items[bounds[b] : bounds[b + 1]].data, int(at[b]))

        # Two buffers, reused (fresh pages would fault in each time): a chunk's items are
        # written to their buckets while the next chunk's are sorted into the other (``then``
        # waits for the write before: a buffer's last write is done before it is filled again)
        buffers = [np.empty(0, np.uint8)] * 2
        for k, (lo, chunk, ends) in enumerate(_chunks(bodies)):  # pass 1: in the order they are
            if len(buffers[k % 2]) < len(chunk):
                buffers[k % 2] = np.empty(len(chunk), np.uint8)
            items = buffers[k % 2]
            places_read = slot[lo : lo + len(ends) - 1]
            bounds = _to_buckets(chunk, ends, places_read, edges, arrived, filled, items)
            release_rows(places_read)
            release(arrived)
            sizes = np.diff(bounds)
            beside.then(write, items, bounds, sizes, cursor.copy())
            cursor += sizes
        beside.wait()
        for b in range(len(edges) - 1):  # pass 2: a bucket at a time, put in order
            lo, hi = int(edges[b]), int(edges[b + 1])
            base = int(offsets[lo])
            bucket_bytes = np.frombuffer(os.pread(scratch.fileno(), int(offsets[hi]) - base, base), np.uint8)
            punch(scratch.fileno(), 0, base + len(bucket_bytes))  # read, as those before: their room goes
            items = np.empty(len(bucket_bytes), np.uint8)
            _from_bucket(bucket_bytes, arrived[lo:hi], offsets, base, items)
            release_rows(arrived[lo:hi])
            release(offsets)  # (the frames made of the bucket beside read them too)
            yield int(group_at[b]), int(group_at[b + 1]), items


@numba.njit(cache=True, nogil=True)
def _to_buckets(
    chunk: np.ndarray,
    ends: np.ndarray,
    places: np.ndarray,
    edges: np.ndarray,
    arrived: np.ndarray,
    filled: np.ndarray,
    out: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled
    # A counting sort of a chunk's items by bucket, in two passes over it: item ``i``
    # (``chunk[ends[i]:ends[i + 1]]``, at ``places[i]`` in the order, -1: not in it) goes to
    # ``out`` after the items of the buckets before its own and of its bucket before it, and
    # its place to ``arrived`` after its bucket's so far (``filled``). Each bucket's bytes in
    # ``out``: from ``bounds[b]`` to ``bounds[b + 1]``.
    bucket = np.empty(len(places), np.int32)
    bounds = np.zeros(len(edges), np.int64)
    for i in range(len(places)):
        b = np.searchsorted(edges, places[i], side="right") - 1  # -1 before ``edges[0]``, 0
        bucket[i] = b
        if b >= 0:
            bounds[b + 1] += ends[i + 1] - ends[i]
    for b in range(1, len(bounds)):
        bounds[b] += bounds[b - 1]
    at = bounds[:-1].copy()
    for i in range(len(places)):
        b = bucket[i]
        if b >= 0:
            copy(out, at[b], chunk, ends[i], ends[i + 1] - ends[i])
            at[b] += ends[i + 1] - ends[i]
            arrived[filled[b]] = places[i]
            filled[b] += 1
    return bounds


@numba.njit(cache=True, nogil=True)
def _from_bucket(
    read: np.ndarray, came: np.ndarray, offsets: np.ndarray, base: int, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    # A bucket's items as they came (``read``, item ``came[i]`` after those before it) to
    # where each goes in ``out``: its offset in the order, less ``base``, the bucket's own.
    r = 0
    for i in range(len(came)):
        start, length = offsets[came[i]], offsets[came[i] + 1] - offsets[came[i]]
        copy(out, start - base, read, r, length)
        r += length


def punch(fd: int, offset: int, length: int) -> None:
    """Free the disk room of ``length`` bytes of the file ``fd`` from ``offset`` (they read as
    zeros after), where the file system can (else nothing happens): the frames' scratch file
    shrinks as its buckets are read back, while the snapshot file grows (at 1e8 items, the
    bucket file is ~11 GB)."""
    if _fallocate is not None and length > 0:
        _fallocate(fd, 3, offset, length)  # FALLOC_FL_PUNCH_HOLE | FALLOC_FL_KEEP_SIZE


def _chunks(bodies: Packed | Framed) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """``(first item, bytes, ends)`` of ``bodies``' items in order, ~``PASS_BYTES`` at a time
    (``ends``: each item's start in ``bytes``, and the end), each let go after it is used."""
    if isinstance(bodies, Packed):
        for lo, hi in bodies.steps(PASS_BYTES):
            base = bodies.offsets[lo]
            yield lo, bodies.array[base : bodies.offsets[hi]], bodies.offsets[lo : hi + 1] - base
        return
    bodies.read_all()
    decompress, first, offsets = _decompressor().decompress, bodies.first, bodies.offsets
    frames = _cuts(offsets[first], PASS_BYTES)  # the frames decoded at a time
    for f, g in itertools.pairwise(frames.tolist()):
        lo, hi = int(first[f]), int(first[g])
        decoded = [
            decompress(bodies.frames[a:z].data) for a, z in itertools.pairwise(bodies.at[f : g + 1].tolist())
        ]
        yield lo, np.frombuffer(b"".join(decoded), np.uint8), offsets[lo : hi + 1] - offsets[lo]
        bodies.release()


def _cuts(offsets: np.ndarray, size: int) -> np.ndarray:
    """The first item of each group, then n: a group ends at the first item that starts
    ``size`` bytes or more after its own first item (an item bigger is a group alone)."""
    n = len(offsets) - 1
    first = [0]
    while first[-1] < n:
        at = int(np.searchsorted(offsets, offsets[first[-1]] + size, side="left"))
        first.append(min(n, max(first[-1] + 1, at)))
        if not len(first) % 4096:  # mapped: the pages the searches read, handed back
            release(offsets)
    release(offsets)
    return np.asarray(first, np.int64)


def places_in(order: np.ndarray, length: int, spill: Path | None = None) -> np.ndarray:
    """Each of ``length`` positions' place in ``order`` (-1: not in it). With ``spill``, a
    directory: in a file there, made a step of ``order`` at a time, the pages written handed
    back after each (4 bytes an item not held)."""
    dtype = index_type(len(order))
    if spill is None:
        return placed(order, np.full(length, -1, dtype))
    out = scratch_array(spill, length, dtype)
    return placed(order, filled(out, -1) if len(order) < length else out)  # else each is written


class Framed:
    """Item bodies kept as ``framed_arrays`` made them (mapped from a file, its reads checked
    by ``watch``): read like a ``Packed``, a frame decoded at a time. Decoded frames lie in
    an arena of the items' length (virtual memory: a page is only held once written) where
    their offsets say, so a join copies the items straight from it, as ``Packed.join`` does;
    ``decoded`` (None: one of its own, of ``CACHE_BYTES``) says which frames stay there."""

    def __init__(
        self,
        frames: np.ndarray,
        at: np.ndarray,
        first: np.ndarray,
        offsets: np.ndarray,
        watch: ReadWatch | None = None,
        decoded: DecodedFrames | None = None,
    ) -> None:
        self.frames, self.at, self.first, self.offsets = frames, at, first, offsets
        self.watch = watch
        self.decoded = DecodedFrames(CACHE_BYTES) if decoded is None else decoded
        self.places = watch.places([frames, offsets]) if watch is not None else UNWATCHED[2]
        # Whether each frame's entries of the index (``first``, ``at``) are checked: a frame's
        # once, not on every answer (1 B a frame of ~16 KiB of items)
        self._indexed = np.zeros(len(first) if watch is not None else 0, np.bool_)
        # Each frame: 0 not in the arena, 1 in it, 3 in it and read since ``decoded`` last looked
        self.present = np.zeros(max(len(first) - 1, 0), np.uint8)
        self._arena: np.ndarray | None = None  # made by the first frame decoded
        self._map: mmap.mmap | None = None
        self.ref = weakref.ref(self)

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, i: int) -> bytes:
        return self.join(np.array([i], np.int64))

    def join(self, positions: np.ndarray, sep: bytes = b",", ends: tuple[bytes, bytes] = (b"", b"")) -> bytes:
        """``Packed.join``: one compiled call over the arena when the items' frames are in
        it (a pan's are, mostly); else their frames are read, checked and decoded into it
        first."""
        if not len(positions):
            return ends[0] + ends[1]
        head, tail = end_arrays(ends)
        watch, lock = self.watch, self.decoded.lock
        marks, pending = (watch.marks, watch.pending) if watch is not None else UNWATCHED[:2]
        args = (
            self.present,
            self.first,
            self.offsets,
            positions,
            sep[0],
            head,
            tail,
            marks,
            pending,
            self.places,
        )
        arena = self._arena
        for _ in range(2):
            if arena is None:
                break
            with lock:
                out = _join_decoded(arena, *args)
            if len(out):
                return out[:-1].tobytes()
            if watch is None or not pending[0]:  # a frame not decoded: below
                break
            watch.settle()  # the items' offsets, read for the first time: checked before their use
        frames = self._frames_of(positions)
        todo = frames[self.present[frames] == 0]
        while True:  # decoded out of the lock (a first read waits for the disk), kept under it
            if len(todo) > 1:
                self._prefetch(todo)
            made = [(f, self._decode(f)) for f in todo.tolist()]
            with lock:
                arena = self._arena if self._arena is not None else self._made()
                for f, data in made:
                    self._keep(f, data)
                out = _join_decoded(arena, *args)
                for f, _ in made:  # read once: no second chance until read again
                    self.present[f] = 1
                self.decoded.trim()
            if len(out):
                return out[:-1].tobytes()
            if len(todo) == len(frames):
                raise AssertionError("the items' frames were decoded, yet a join of them found one missing")
            todo = frames  # one was let go meanwhile, for another thread's join: all of them, this time

    def read_all(self) -> None:
        """Before every item is read: every block of them checked."""
        if self.watch is not None:
            self.watch.check(self.frames, self.at, self.first, self.offsets)

    def release(self) -> None:
        release(self.frames)

    def unpacked(self, spill: Path | None = None) -> Packed:
        """The bodies decompressed end to end, each frame once (with ``spill``, a directory: into
        a ``Spill`` there, written a step at a time)."""
        with Spill(spill) if spill is not None else InMemory() as out:
            for _, items, _ in _chunks(self):
                out.write(items.data)
            return Packed(out.mapped(), self.offsets)

    def take(self, order: np.ndarray, spill: Path | None = None) -> Packed:
        """``Packed.take``: each frame decoded once, in order (with ``spill``, a directory: the
        items put in order through buckets, into a ``Spill`` there; see ``taken``)."""
        if spill is None:
            return self.unpacked().take(order)
        return taken(self, order, spill)

    def _frames_of(self, positions: np.ndarray) -> np.ndarray:
        """The frames the items at ``positions`` lie in, sorted. Mapped from a file, the items'
        offsets and those frames' entries of the index are checked first, not the whole index
        (12 MB at 1e8 items, read from the disk by a first answer); a frame's entries once, then
        it is known checked. The search reads entries not yet checked: the checked bounds of the
        frames it finds confirm them (``first`` is sorted), and should they not, the whole index
        is checked, which finds the bad block."""
        frames, confirmed = _located(self.first, positions)
        watch = self.watch
        if watch is None:
            return frames
        if mark_rows(positions, watch.marks, watch.pending, self.places):
            watch.settle()
        new = frames[~self._indexed[frames]]
        if len(new):
            ends = [(int(f), int(f) + 2) for f in new.tolist()]
            watch.check(*(self.first[a:b] for a, b in ends), *(self.at[a:b] for a, b in ends))
            self._indexed[new] = True
        if not confirmed:
            watch.check(self.first)
            raise AssertionError("the frames' index is out of order, yet its blocks are sound")
        return frames

    def _prefetch(self, frames: np.ndarray) -> None:
        """Have the blocks of ``frames`` read from the file at once, not one frame's after
        another's."""
        if self.watch is not None:
            shift, at = int(self.places[0]), int(self.places[1])
            lo, hi = (at + self.at[frames]) >> shift, (at + self.at[frames + 1] - 1) >> shift
            self.watch.prefetch(
                np.concatenate([np.arange(a, b + 1) for a, b in zip(lo.tolist(), hi.tolist(), strict=True)])
            )

    def _decode(self, f: int) -> bytes:
        """Frame ``f`` read (its blocks checked) and decompressed.

        :raises SnapshotCorrupt: if a block of it is bad
        """
        lo, hi = self.at[f : f + 2].tolist()
        data = self.frames[lo:hi]
        if self.watch is not None:
            self.watch.check(data)
        decoded = _decompressor().decompress(data.data)
        start, end = self._span(f)
        if len(decoded) != end - start:  # its blocks are sound: never, short of a bug
            raise AssertionError(f"frame {f} decoded to {len(decoded)} bytes, not its items' {end - start}")
        return decoded

    def _span(self, f: int) -> tuple[int, int]:
        """Where frame ``f``'s items lie in the arena."""
        return int(self.offsets[self.first[f]]), int(self.offsets[self.first[f + 1]])

    def _made(self) -> np.ndarray:
        """The arena, the items' whole length of it mapped (none of it held yet)."""
        if self.watch is not None:
            self.watch.check(self.offsets[-1:])
        size = int(self.offsets[-1])
        if size:
            self._map = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | _NORESERVE)
            self._arena = np.frombuffer(self._map, np.uint8)
        else:
            self._arena = np.zeros(0, np.uint8)
        return self._arena

    def _keep(self, f: int, data: bytes) -> None:
        """Frame ``f``'s ``data`` into the arena, kept there as ``decoded`` says (its lock held)."""
        if self.present[f]:  # another thread decoded it meanwhile
            return
        lo, hi = self._span(f)
        assert self._arena is not None
        self._arena[lo:hi] = np.frombuffer(data, np.uint8)
        self.present[f] = 1
        self.decoded.admit(self, f, hi - lo)

    def forget(self, f: int) -> None:
        """Frame ``f`` out of the arena, its pages handed back but those a frame still there
        has bytes in; ``decoded``'s lock held."""
        self.present[f] = 0
        lo, hi = self._span(f)
        page = mmap.PAGESIZE
        start, end = lo // page * page, -(-hi // page) * page
        if start < end and self._held(f, start, -1):
            start += page
        if start < end and self._held(f, end - page, 1):
            end -= page
        if start < end and self._map is not None:
            self._map.madvise(mmap.MADV_DONTNEED, start, min(end, len(self._map)) - start)

    def _held(self, f: int, page: int, step: int) -> bool:
        """Whether a frame still in the arena, before ``f`` (``step`` -1) or after it (1), has
        bytes in the page at ``page`` (frames smaller than a page share it with several)."""
        g = f + step
        while 0 <= g < len(self.present):
            lo, hi = self._span(g)
            if (hi <= page) if step < 0 else (lo >= page + mmap.PAGESIZE):
                return False
            if self.present[g] and lo < hi:
                return True
            g += step
        return False


@numba.njit(cache=True, nogil=True)
def _located(first: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, bool]:  # pragma: no cover
    """``(frames, confirmed)``: the frames (``first``: each one's first item, and n) the items
    at ``positions`` lie in, sorted and each once; and whether each item lies within its
    frame's bounds, as read. O(n + frames spanned): a sort of the items' frames took a fifth
    of a viewport's CPU."""
    n, count = len(positions), len(first) - 1
    frame_of = np.empty(n, np.int64)
    confirmed, f = True, 0
    for i in range(n):
        p = positions[i]
        if not (0 <= f < count and first[f] <= p < first[f + 1]):  # mostly the item before's frame
            f = np.searchsorted(first, p, side="right") - 1
            confirmed &= 0 <= f < count and first[f] <= p < first[f + 1]
        frame_of[i] = f
    if n == 0:
        return frame_of, confirmed
    lo = frame_of.min()
    span = frame_of.max() - lo + 1
    if span > 4 * n + 64:  # spread over many more frames than items: sorted instead
        return np.unique(frame_of), confirmed
    used = np.zeros(span, np.bool_)  # each frame spanned: whether an item lies in it
    for i in range(n):
        used[frame_of[i] - lo] = True
    return lo + np.flatnonzero(used), confirmed


@numba.njit(cache=True, nogil=True)
def _join_decoded(
    arena: np.ndarray,
    present: np.ndarray,
    first: np.ndarray,
    offsets: np.ndarray,
    positions: np.ndarray,
    sep: int,
    head: np.ndarray,
    tail: np.ndarray,
    marks: np.ndarray,
    pending: np.ndarray,
    places: np.ndarray,
) -> np.ndarray:  # pragma: no cover
    """The items at ``positions`` joined by ``sep`` between ``head`` and ``tail``, out of
    ``arena`` (the items decoded where their ``offsets`` say), then one byte more. Empty when
    it cannot say: an item's offsets not checked yet (marked read: check them, then ask
    again), or its frame not in the arena (``present``: marked read when it is)."""
    if mark_rows(positions, marks, pending, places):  # its own rows: not another thread's pending reads
        return np.empty(0, np.uint8)
    count = len(first) - 1
    size = len(head) + len(positions) - 1 + len(tail) + 1
    f = -1
    for p in positions:
        if not (0 <= f < count and first[f] <= p < first[f + 1]):  # mostly the item before's frame
            f = np.searchsorted(first, p, side="right") - 1
            if not (0 <= f < count and first[f] <= p < first[f + 1]) or not present[f]:
                return np.empty(0, np.uint8)
            present[f] = 3
        size += offsets[p + 1] - offsets[p]
    out = np.empty(size, np.uint8)
    copy(out, 0, head, 0, len(head))
    k = len(head)
    for i in range(len(positions)):
        if i:
            out[k] = sep
            k += 1
        p = positions[i]
        copy(out, k, arena, offsets[p], offsets[p + 1] - offsets[p])
        k += offsets[p + 1] - offsets[p]
    copy(out, k, tail, 0, len(tail))
    return out


class DecodedFrames:
    """Which decoded frames the ``Framed`` that share it keep (a worker's documents:
    ``VANTAGE_FRAMES_MB``): at most ``limit`` bytes of them, those read least lately let go
    first (a second chance: a frame read since it was last looked at goes round again). A
    join reads a frame with ``lock`` held, so none is let go under it."""

    def __init__(self, limit: int) -> None:
        self.bytes, self.limit = 0, limit
        self.lock = threading.Lock()
        self._queue: deque[tuple[weakref.ref[Framed], int, int]] = deque()  # (whose, frame, bytes)

    def admit(self, framed: Framed, f: int, nbytes: int) -> None:
        """``framed``'s frame ``f`` (``nbytes``) is decoded; ``lock`` held."""
        self._queue.append((framed.ref, f, nbytes))
        self.bytes += nbytes

    def trim(self) -> None:
        """Let frames go until at most ``limit`` bytes are kept; ``lock`` held."""
        queue = self._queue
        while self.bytes > self.limit and queue:
            ref, f, nbytes = queue.popleft()
            framed = ref()
            if framed is not None and framed.present[f] == 3:  # read since: once more round
                framed.present[f] = 1
                queue.append((ref, f, nbytes))
                continue
            self.bytes -= nbytes  # a document closed since lets its frames go with it
            if framed is not None:
                framed.forget(f)


_LOCAL = threading.local()


def _decompressor() -> zstandard.ZstdDecompressor:
    """This thread's decompressor (one is not safe to share, and costs ~5 us to make)."""
    made = getattr(_LOCAL, "decompressor", None)
    if made is None:
        made = _LOCAL.decompressor = zstandard.ZstdDecompressor()
    return made
