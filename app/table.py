"""A document's items as columns: what the store saves in a few blobs and a snapshot serves from.

A million items as Python objects would cost ~300 bytes each (a str, a dict slot, a bytes
object per answer); as columns they cost their bytes plus 32 for offsets and the id hash index.
Ids are kept JSON-encoded, so a ``leave`` list is a join of slices, never a dump.

An import's columns (its bodies, the bulk of its bytes, its ids and boxes, then its offsets
and id index) can go to a ``Spill``: a file with no name, mapped, that the kernel pages in and
out as it needs, and each pass over them hands back the pages it read, so an import of any
size holds none of them in memory but the pass's.
"""

from __future__ import annotations

import mmap
import os
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property, partial
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec
import numba
import numpy as np

from spatial import _paging
from spatial._copy import copy
from spatial._kernels import UNWATCHED, mark_read
from spatial._paging import STEP_BYTES, Scratch, in_steps, mapping, new_array, release, release_rows
from spatial._sorting import sorted_keys
from spatial.quadtree import ReadWatch

if TYPE_CHECKING:
    from .frames import Framed

__all__ = ["Edit", "ItemTable", "Packed", "Spill", "fnv1a", "release"]

# An edit as the store keeps it: item id, version, box, body (box and body None: deleted)
Edit = tuple[str, int, "tuple[float, ...] | None", "bytes | None"]


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


class _Memory:
    """A ``Spill``'s interface over bytes kept in memory."""

    def __init__(self) -> None:
        self._parts: list[bytes] = []
        self.size = 0

    def __enter__(self) -> _Memory:
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
        head, tail = (np.frombuffer(end, np.uint8) for end in ends)
        watch = self.watch
        if watch is None:
            marks, pending = UNWATCHED[:2]
        else:  # the offsets say how much to copy from where: checked before they are used
            marks, pending = watch.marks, watch.pending
            if _mark_rows(positions, marks, pending, self.places):
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
            buffer, offsets = _take(self.array, self.offsets, order)
            return Packed(buffer.tobytes(), offsets)
        offsets = offsets_in(self.offsets, order)
        self.release()  # the offsets read at random (mapped: a spilled table's)
        ends = offsets[1:]
        with Spill(spill) as out:
            start = 0
            while start < len(order):  # a step of about STEP_BYTES at a time
                done = int(ends[start - 1]) if start else 0
                stop = max(start + 1, int(np.searchsorted(ends, done + STEP_BYTES, side="right")))
                out.write(_take(self.array, self.offsets, order[start:stop])[0].data)
                self.release()
                start = stop
            return Packed(out.mapped(), offsets)

    def spliced(self, at: dict[int, bytes], tail: Sequence[bytes] = (), spill: Path | None = None) -> Packed:
        """These items with those at the positions of ``at`` replaced by its items, then the
        items of ``tail``: copied a run at a time (with ``spill``, a directory: into a ``Spill``
        there, the pages read released after each step)."""
        self.read_all()
        offsets = _spliced_offsets(self.offsets, {p: len(item) for p, item in at.items()}, tail, spill)
        with Spill(spill) if spill is not None else _Memory() as out:
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

    def _copy(self, lo: int, hi: int, out: Spill | _Memory) -> None:
        """Bytes ``[lo, hi)`` of the buffer to ``out``, a step at a time, each step's pages
        handed back once read (when it is mapped)."""
        for step in range(lo, hi, STEP_BYTES):
            out.write(memoryview(self.buffer)[step : min(step + STEP_BYTES, hi)])
            self.release()


@dataclass(frozen=True)
class ItemTable:
    """Items by position: JSON-encoded ids, response bodies and (n, 4) float64 boxes.

    Ids are unique once merged (``merge`` keeps the last of a repeated id).
    """

    ids: Packed
    bodies: Packed | Framed  # Framed: mapped from a snapshot file
    boxes: np.ndarray
    watch: ReadWatch | None = None  # mapped from a file: its boxes and id index are checked before use

    @classmethod
    def of(cls, ids: Sequence[str], boxes: np.ndarray, bodies: Sequence[bytes]) -> ItemTable:
        """Items in the order given; an id given twice is resolved by ``merge``."""
        return cls(Packed.of(list(map(msgspec.json.encode, ids))), Packed.of(bodies), boxes.reshape(-1, 4))

    @classmethod
    def merge(
        cls, tables: Sequence[ItemTable], deleted: Iterable[str] = (), spill: Path | None = None
    ) -> ItemTable:
        """The items of ``tables`` in order, an id given again replacing the earlier one where
        that one stood (an upsert: a document's order stays the import's), without the
        ``deleted`` ids.

        Only the ids are joined to find what survives; bodies and boxes are copied once, from
        each table straight into the result (twice when an upsert moves an item back to its
        place); with ``spill``, a directory, the bodies are copied into a ``Spill`` there.
        """
        for table in tables:
            table.read_all()
        scratch = None if spill is None else partial(scratch_array, spill)
        if len(tables) == 1:  # the ids as they are, and their index if made already (by a pack)
            ids = tables[0].ids
            index = tables[0].__dict__.get("_index") or _id_index(ids, scratch)
        else:
            ids = Packed.concat([t.ids for t in tables])
            index = _id_index(ids, scratch)
        drop, place = _repeated(ids, index)
        for item_id in deleted:
            drop[list(_positions(ids, index, msgspec.json.encode(item_id)))] = True
        if not drop.any() and len(tables) == 1:
            tables[0].__dict__["_index"] = index  # the cached_property's slot: made once
            return tables[0]
        keep = ~drop
        keeps = np.split(keep, np.cumsum([len(t) for t in tables[:-1]]))
        merged = cls(
            Packed.gather([ids], [keep]) if drop.any() else ids,
            Packed.gather([t.bodies.unpacked(spill) for t in tables], keeps, spill),
            np.concatenate([t.boxes[k] for t, k in zip(tables, keeps, strict=True)]),
        )
        if not drop.any():
            merged.__dict__["_index"] = index  # the cached_property's slot: the ids are the same
            return merged
        if place is None:  # no id repeated: each survivor stands where it stood
            return merged
        order = np.argsort(place[keep], kind="stable")  # each survivor where its id first stood
        if (order == np.arange(len(order))).all():
            return merged
        return merged.take(order, spill)

    @classmethod
    def empty(cls) -> ItemTable:
        return cls.of([], np.empty((0, 4)), [])

    def __len__(self) -> int:
        return len(self.boxes)

    def item_id(self, pos: int) -> str:
        return msgspec.json.decode(self.ids[pos])

    def position(self, item_id: str) -> int | None:
        """Where ``item_id`` is, or None. Cost: O(log n), a binary search of the id hashes
        (mapped from a file: each block it reads checked, not the whole index)."""
        return next(_positions(self.ids, self._index, msgspec.json.encode(item_id), self.watch), None)

    def positions(self, item_ids: Sequence[str]) -> list[int | None]:
        """``position`` of each of ``item_ids``, looked up together: one compiled search of the
        id hashes for them all, where ``position`` takes a Python step a probe (an open
        catching up on thousands of edits: ~20x sooner)."""
        hashes, _ = self._index
        keys = [msgspec.json.encode(item_id) for item_id in item_ids]
        wanted = _hashes_of(Packed.of(keys), hashes.dtype)
        starts = np.searchsorted(hashes, wanted).tolist()  # unchecked: each one's bracket is
        return [
            next(_positions(self.ids, self._index, key, self.watch, (start, h)), None)
            for key, start, h in zip(keys, starts, wanted, strict=True)
        ]

    def take(self, order: np.ndarray, spill: Path | None = None) -> ItemTable:
        """The items at ``order`` (positions), in that order, in arrays of their own (with
        ``spill``, a directory: the bodies in a ``Spill`` there)."""
        return ItemTable(self.ids.take(order), self.bodies.take(order, spill), self.read_boxes()[order])

    def read_boxes(self) -> np.ndarray:
        """``boxes``, checked first when mapped from a file."""
        if self.watch is not None:
            self.watch.check(self.boxes)
        return self.boxes

    def read_all(self) -> None:
        """Before Python reads the table as a whole: every block of it checked."""
        self.ids.read_all()
        self.bodies.read_all()
        if self.watch is not None:
            self.watch.check(self.boxes, *self._index)

    def halve_hashes(self, spill: Path | None = None) -> None:
        """Keep the id index's hashes as a file keeps them, their high 32 bits: 4 bytes an item
        less through a build. For a table merged already: a merge's search for repeated ids
        would meet ~n**2 / 2**33 twins (a lookup compares the few ids whose half-hash matches).
        With ``spill``, a directory, made into a ``Spill`` there a step at a time, not held
        (the table an import merged into itself lives on through the build)."""
        hashes, order = self._index
        if spill is None or hashes.dtype == np.uint32:
            halves = high_halves(hashes)
        else:
            with Spill(spill) as out:
                for _, step in in_steps(hashes):
                    out.write(high_halves(step).data)
                halves = np.frombuffer(out.mapped(), np.uint32)
        self.__dict__["_index"] = (halves, order)
        release(hashes)  # read through: mapped (a spilled pack's), its pages handed back

    def release(self) -> None:
        """Hand back the pages of its columns mapped from a file (``spilled``) read so far."""
        self.ids.release()
        self.bodies.release()
        for column in (*self.__dict__.get("_index", ()), self.boxes):
            release(column)

    def spilled(self, directory: Path) -> ItemTable:
        """This table with its ids, its bodies' offsets, its id index and its boxes in a
        ``Spill`` in ``directory``, mapped (those already mapped from a file stay). An import's
        build reads these in a few passes, each a step at a time or released after
        (``release``), so the peaks of the overview's and the tree's builds hold none of them:
        ~60 bytes an item less."""
        if not isinstance(self.bodies, Packed):  # mapped from a snapshot file: all of it
            return self
        columns = (self.ids.array, self.ids.offsets, self.bodies.offsets, *self._index, self.boxes)
        moving = [k for k, column in enumerate(columns) if mapping(column) is None]
        if not moving:
            return self
        moved = list(columns)
        for k, column in zip(moving, spilled_arrays([columns[k] for k in moving], directory), strict=True):
            moved[k] = column
        ids, id_offsets, offsets, hashes, order, boxes = moved
        table = ItemTable(
            Packed(ids.data if ids is not columns[0] else self.ids.buffer, id_offsets),
            Packed(self.bodies.buffer, offsets),
            boxes,
        )
        table.__dict__["_index"] = (hashes, order)  # the cached_property's slot
        return table

    @cached_property
    def _index(self) -> tuple[np.ndarray, np.ndarray]:
        return _id_index(self.ids)


def scratch_array(directory: Path, length: int, dtype: type[np.generic]) -> np.ndarray:
    """An array of ``length`` values, not filled in, in a file with no name in ``directory``,
    mapped shared: what is written to it goes to the page cache, and ``release`` hands its
    pages back with nothing lost. The file goes with the array's last view. Its room on the
    disk is taken at once: a full disk raises ``OSError`` (ENOSPC) here, where a write to a
    page of a sparse file would kill the process (SIGBUS).

    :raises OSError: if the disk has no room for it
    """
    size = length * np.dtype(dtype).itemsize
    if not size:  # an empty file cannot be mapped
        return np.empty(0, dtype)
    directory.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryFile(dir=directory) as file:
        os.posix_fallocate(file.fileno(), 0, size)
        return np.frombuffer(mmap.mmap(file.fileno(), size, access=mmap.ACCESS_WRITE), dtype)


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


def _id_index(ids: Packed, scratch: Scratch | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Id hashes sorted, and the position of each (int32 while they fit): 12 bytes an item,
    where a dict costs ~100. A file keeps each hash's high 32 bits (still sorted): a few more
    ids to compare at a lookup (one in ~4e9 / n has a twin), 4 bytes an item less. Sorted by
    a radix sort, ties in position order: ``np.argsort``'s stable order, ~3x sooner; with
    ``scratch``, made and sorted in its files a run at a time (``sorted_keys``), not held."""
    hashes = new_array(scratch, len(ids), np.uint64)
    for lo, hi in ids.steps():  # mapped ids (a spilled import's) handed back a step at a time
        out = hashes[lo:hi]
        out[:] = fnv1a(ids.array, ids.offsets[lo : hi + 1])
        release_rows(out)
    order, hashes = sorted_keys(hashes, 64, scratch)
    return hashes, order


def high_halves(hashes: np.ndarray) -> np.ndarray:
    """Id index hashes as a file keeps them, their high 32 bits (kept so already, or not)."""
    return hashes if hashes.dtype == np.uint32 else (hashes >> np.uint64(32)).astype(np.uint32)


def _positions(
    ids: Packed,
    index: tuple[np.ndarray, np.ndarray],
    key: bytes,
    watch: ReadWatch | None = None,
    searched: tuple[int, np.unsignedinteger] | None = None,
) -> Iterator[int]:
    """Every position of ``ids`` holding ``key`` (a JSON-encoded id: one, once merged); with
    ``watch``, each entry of the index read is checked first. ``searched``: where its hash
    goes, and the hash, if searched already (a binary search, unchecked)."""
    hashes, order = index
    if searched is None:
        h = _hashes_of(Packed.of([key]), hashes.dtype)[0]
        lo = int(np.searchsorted(hashes, h)) if watch is None else _search(hashes, h, watch)
    else:
        lo, h = searched
        if watch is not None:  # a binary search ends between the two entries it probed last:
            watch.check(hashes[max(lo - 1, 0) : lo + 1])  # sound, they place it, whatever it read before
    for i in range(lo, len(hashes)):
        if watch is not None:
            watch.check(hashes[i : i + 1], order[i : i + 1])
        if hashes[i] != h:
            break
        if ids[order[i]] == key:
            yield int(order[i])


def _hashes_of(keys: Packed, dtype: np.dtype) -> np.ndarray:
    """The id index's hashes of ``keys`` (JSON-encoded ids), in ``dtype``: a file's keeps
    the high halves."""
    hashes = fnv1a(np.frombuffer(keys.buffer, np.uint8), keys.offsets)
    return high_halves(hashes) if dtype == np.uint32 else hashes


def _search(hashes: np.ndarray, h: np.unsignedinteger, watch: ReadWatch) -> int:
    """``np.searchsorted(hashes, h)``, a probe at a time, the block of each checked first."""
    lo, hi = 0, len(hashes)
    while lo < hi:
        mid = (lo + hi) // 2
        watch.check(hashes[mid : mid + 1])
        lo, hi = (mid + 1, hi) if hashes[mid] < h else (lo, mid)
    return lo


def _repeated(ids: Packed, index: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray | None]:
    """Mask of ids that come again later (the later one wins, as in an upsert), and where each
    id first stood (its own position for most; None when no id comes again, as in most
    imports: 8 bytes an item not made)."""
    hashes, order = index
    drop = np.zeros(len(ids), bool)
    starts = _twins(hashes)
    if not len(starts):
        return drop, None
    place = np.arange(len(ids), dtype=np.int64)
    for start in starts.tolist():  # rare: a repeated id (or a hash collision), checked by hand
        stop = start + 1
        while stop < len(hashes) and hashes[stop] == hashes[start]:
            stop += 1
        first: dict[bytes, int] = {}
        last: dict[bytes, int] = {}
        for pos in order[start:stop].tolist():  # ascending: the sort is stable
            key = bytes(ids[pos])  # hashable whatever backs the pack (bytes stay themselves)
            if key in last:
                drop[last[key]] = True
            else:
                first[key] = pos
            last[key] = pos
        for key, pos in last.items():
            place[pos] = first[key]
    return drop, place


def _twins(hashes: np.ndarray) -> np.ndarray:
    """Where each run of equal ``hashes`` (sorted) starts, read a step at a time: mapped from
    a file, each step's pages are handed back."""
    again = []  # the rows equal to the one before: rare
    for lo, step in in_steps(hashes):
        before = hashes[lo - 1 : lo] if lo else step[:0]
        joined = np.concatenate((before, step))
        again.append(np.flatnonzero(joined[1:] == joined[:-1]) + (lo if lo else 1))
    rows = np.concatenate(again) if again else np.empty(0, np.int64)
    return rows[~np.isin(rows - 1, rows)] - 1


@numba.njit(cache=True, nogil=True)
def _take(
    array: np.ndarray, offsets: np.ndarray, order: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
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
    pages: 730 MB at 1e8 items), and a window (``WINDOW_BYTES``) is held."""
    length = len(order) + 1
    if spill is None or places is None:
        out = np.empty(length, np.int64)
        out[0] = 0
        _offsets_in(offsets, order, out)
        return out
    out = scratch_array(spill, length, np.int64)
    out[0], total = 0, 0
    for a, b in _paging.windows(len(order), 8, in_file=True):
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
def fnv1a(buffer: np.ndarray, offsets: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """64-bit FNV-1a of each packed item: stable across processes, unlike ``hash``."""
    out = np.empty(len(offsets) - 1, np.uint64)
    for i in range(len(out)):
        h = np.uint64(14695981039346656037)
        for j in range(offsets[i], offsets[i + 1]):
            h = (h ^ np.uint64(buffer[j])) * np.uint64(1099511628211)
        out[i] = h
    return out


@numba.njit(cache=True, nogil=True)
def _mark_rows(
    positions: np.ndarray, marks: np.ndarray, pending: np.ndarray, places: np.ndarray
) -> int:  # pragma: no cover - compiled
    """Report the offsets of the items at ``positions`` read (see ``ReadWatch``); how many
    blocks are newly marked."""
    before = pending[0]
    for p in positions:
        mark_read(marks, pending, places, 1, p, p + 2)
    return pending[0] - before


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
