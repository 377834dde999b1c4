"""A document's items as columns: what the store saves in a few blobs and a snapshot serves from.

A million items as Python objects would cost ~300 bytes each (a str, a dict slot, a bytes
object per answer); as columns they cost their bytes plus 32 for offsets and the id hash index.
Ids are kept JSON-encoded, so a ``leave`` list is a join of slices, never a dump.

The columns are ``Packed`` (``packed``: with the ``Spill`` files an import's columns can go
to), the bodies of a table mapped from a snapshot file ``Framed`` (``frames``).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property, partial
from pathlib import Path

import msgspec
import numba
import numpy as np

from spatial.paging import Scratch, in_steps, mapping, new_array, release, release_rows
from spatial.quadtree import ReadWatch
from spatial.sorting import sorted_keys

from .frames import Framed
from .packed import Packed, Spill, scratch_array, spilled_arrays

__all__ = ["Edit", "ItemTable", "Packed", "Spill", "fnv1a", "release"]

# An edit as the store keeps it: item id, version, box, body (box and body None: deleted)
Edit = tuple[str, int, "tuple[float, ...] | None", "bytes | None"]


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
def fnv1a(buffer: np.ndarray, offsets: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """64-bit FNV-1a of each packed item: stable across processes, unlike ``hash``."""
    out = np.empty(len(offsets) - 1, np.uint64)
    for i in range(len(out)):
        h = np.uint64(14695981039346656037)
        for j in range(offsets[i], offsets[i + 1]):
            h = (h ^ np.uint64(buffer[j])) * np.uint64(1099511628211)
        out[i] = h
    return out
