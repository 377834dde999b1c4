"""Where each of a tree's built ids sits: ``Lookup``, made on a tree's first edit (or given
by a file), and ``settle_rows``, which checks the rows of a mapped array it read."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from . import _walk
from .sorting import found_in

if TYPE_CHECKING:
    from .quadtree import ReadWatch

__all__ = ["Lookup", "settle_rows"]


class Lookup:
    """Where each built id sits. Ids that span at most twice their count (the service's are
    positions 0..n-1) get a dense inverse, O(n) to make; others a sorted copy to search,
    O(n log n): 100 ms for a million ids, once per tree, on its first edit."""

    def __init__(
        self,
        lo: int,
        positions: np.ndarray,
        ids: np.ndarray | None,
        identity_of: int = 0,
        watch: ReadWatch | None = None,
    ) -> None:
        self.lo, self.positions, self.ids = lo, positions, ids  # ids None: dense
        self.identity_of = identity_of  # n when the ids are 0..n-1 in order
        self.watch = watch  # checks each entry of ``positions`` read (dense, mapped from a file)

    @classmethod
    def of(cls, ids: np.ndarray) -> Lookup:
        if not len(ids):
            return cls(0, np.empty(0, np.int64), None)
        lo, hi = int(ids.min()), int(ids.max())
        if hi - lo < 2 * len(ids):
            positions = np.full(hi - lo + 1, -1, np.int64)
            positions[ids - lo] = np.arange(len(ids))
            return cls(lo, positions, None)
        order = np.argsort(ids, kind="stable")
        return cls(lo, order, ids[order])

    @classmethod
    def identity(cls, n: int) -> Lookup:
        """Ids ``0..n-1``, each where it is: nothing to make or read."""
        return cls(0, np.empty(0, np.int64), None, n)

    def find(self, item_id: int) -> int | None:
        if self.identity_of:
            return item_id if 0 <= item_id < self.identity_of else None
        if self.ids is None:
            k = item_id - self.lo
            if self.watch is not None and 0 <= k < len(self.positions):
                self.watch.check(self.positions[k : k + 1])
            pos = int(self.positions[k]) if 0 <= k < len(self.positions) else -1
            return pos if pos >= 0 else None
        i = int(np.searchsorted(self.ids, item_id))
        return int(self.positions[i]) if i < len(self.ids) and self.ids[i] == item_id else None

    def find_many(self, item_ids: np.ndarray) -> np.ndarray:
        """``find`` of each of ``item_ids`` at once: their slots, -1 for those not here."""
        item_ids = np.asarray(item_ids, np.int64)
        if self.identity_of:
            return np.where((item_ids >= 0) & (item_ids < self.identity_of), item_ids, -1)
        if self.ids is None:  # dense: each id's entry at its offset, -1 where none is
            k = item_ids - self.lo
            hit = (k >= 0) & (k < len(self.positions))
            at = k[hit]
            if self.watch is not None:
                settle_rows(self.watch, self.positions, at)
        else:
            at, hit = found_in(self.ids, item_ids)
        found = np.full(len(item_ids), -1, np.int64)
        found[hit] = self.positions[at]
        return found

    @property
    def nbytes(self) -> int:
        return self.positions.nbytes + (self.ids.nbytes if self.ids is not None else 0)


def settle_rows(watch: ReadWatch, array: np.ndarray, rows: np.ndarray) -> None:
    """Report ``rows`` of ``array`` read, as compiled code does (``_walk.mark_read``), and
    check their blocks: each block once, however many of the rows it holds."""
    shift, at, row = watch.places([array]).tolist()
    blocks = np.unique((at + rows * row) >> shift)
    blocks = blocks[watch.marks[blocks] != 1]
    watch.marks[blocks] |= 2
    watch.pending[0] += len(blocks)
    watch.pending[1 + (blocks >> _walk.READ_RUN)] = 1
    watch.settle()
