"""Keys sorted with their positions: in memory in place, or in files a run at a time.

A build's keys (the tree's, 8 bytes an item, and its positions, 4) sorted in memory hold 12
bytes an item through the sort: 1.2 GB at 1e8 items. In files, one pass of a radix sort
spreads them out of place by their top digit, a step at a time, each step's pages handed
back; then each run of whole buckets (the ``sort_bytes`` of the ``budget.MemoryBudget``
held) is sorted in memory and written back, and a bucket larger than a run is spread again
by its next digit. The build then holds a run, whatever the count.

What it promises: ``sorted_keys`` gives one answer, a stable sort's, in memory and in files
at any budget; ``found_in`` finds sorted keys without sorting them again.
"""

from __future__ import annotations

import numpy as np

from . import _kernels
from .budget import current
from .paging import Scratch, in_steps, new_array, release, release_rows, steps

__all__ = ["found_in", "sorted_keys"]

_DIGIT = 11  # bits of a digit of a pass out of place, as ``radix_sort``'s


def found_in(keys: np.ndarray, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each of ``wanted`` is in ``keys`` (sorted), for those that are: ``(where,
    found)``, ``where`` as long as ``found`` is true. A search of each, not ``np.isin``,
    which sorts ``keys`` again every call. Cost: O(m log n) for m wanted of n keys.

    >>> where, found = found_in(np.array([2, 5, 9]), np.array([9, 3, 2]))
    >>> where.tolist(), found.tolist()
    ([2, 0], [True, False, True])
    """
    if not len(keys):
        return np.empty(0, np.int64), np.zeros(len(wanted), bool)
    at = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
    found = keys[at] == wanted
    return at[found], found


def sorted_keys(
    keys: np.ndarray, bits: int, scratch: Scratch | None = None, run_bytes: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(order, keys)``: the positions of ``keys`` (uint64, their low ``bits`` compared) in
    key order, ties in position order (int32 while they fit), and the keys so sorted: a
    stable radix sort's answer. ``keys`` are overwritten. In memory, they are sorted in
    place; with ``scratch`` (``keys`` then in a file of it), both come back in its files,
    sorted a run of about ``run_bytes`` (None: the ``sort_bytes`` of the budget held,
    ``budget.current()``) at a time. Cost: O(n) a pass, a pass for each 11 of ``bits``.

    >>> order, keys = sorted_keys(np.array([3, 1, 2, 1], np.uint64), 8)
    >>> order.tolist(), keys.tolist()
    ([1, 3, 2, 0], [1, 1, 2, 3])
    """
    n = len(keys)
    order = new_array(scratch, n, _kernels.index_type(n))
    for lo, step in in_steps(order):
        step[:] = np.arange(lo, lo + len(step), dtype=order.dtype)
    if scratch is None:
        return _kernels.radix_sort(keys, order, bits)
    run_bytes = current().sort_bytes if run_bytes is None else run_bytes
    runs = _Runs(scratch, max(1, run_bytes // (keys.itemsize + order.itemsize)))
    sorted_k, sorted_o = runs.sort((keys, order), 0, n, bits)
    return sorted_o, sorted_k


class _Runs:
    """A sort in files: the keys and positions given, a spare pair as large made once a
    pass goes out of place, and the passes between them."""

    def __init__(self, scratch: Scratch, run: int) -> None:
        self.scratch, self.run = scratch, run
        self.pairs: list[tuple[np.ndarray, np.ndarray]] = []

    def sort(
        self, pair: tuple[np.ndarray, np.ndarray], a: int, b: int, bits: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Rows ``a..b`` of ``pair`` (keys alike above their low ``bits``) sorted: the pair
        that holds them so, ``pair`` or the spare."""
        keys = pair[0]
        while bits > 0 and b - a > self.run:
            shift = (bits - 1) // _DIGIT * _DIGIT
            counts = np.zeros(1 << _DIGIT, np.int64)
            for _, step in in_steps(keys[a:b]):
                _kernels.digit_counts(step, shift, counts)
            if counts.max() < b - a:
                return self._spread(pair, a, b, bits, shift, counts)
            bits = shift  # one digit for all: the next
        if bits > 0 and b - a > 1:
            self._in_memory(pair, a, b, bits)
        return pair  # (no bits left: the keys alike, their positions in the order given)

    def _spread(
        self, pair: tuple[np.ndarray, np.ndarray], a: int, b: int, bits: int, shift: int, counts: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Rows ``a..b`` spread out of place into the other pair by their digit at ``shift``,
        a step at a time, then each run of whole buckets sorted there (a larger bucket spread
        again): the other pair, holding them sorted."""
        other = self._other(pair)
        ends = a + np.cumsum(counts)
        nexts = ends - counts
        for lo, hi in steps(b - a, pair[0].itemsize + pair[1].itemsize):
            keys, order = (column[a + lo : a + hi] for column in pair)
            _kernels.distribute(keys, order, shift, nexts, other[0], other[1])
            for column in (keys, order):
                release_rows(column)
            for column in other:  # written at up to 2,048 places: its pages handed back whole
                release(column)
        c = a  # the start of the run of buckets being gathered
        for d, e in zip((ends - counts).tolist(), ends.tolist(), strict=True):
            if e - c <= self.run:
                continue
            if d > c:  # the buckets before this one: one run, sorted by this digit too
                self._in_memory(other, c, d, bits)
            if e - d > self.run:  # a bucket past a run: spread again by its next digit
                if self.sort(other, d, e, shift) is not other:
                    _copy(pair, other, d, e)
                c = e
            else:
                c = d
        if b - c > 1:
            self._in_memory(other, c, b, bits)
        return other

    def _other(self, pair: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        if not self.pairs:
            self.pairs.append(pair)
            self.pairs.append(tuple(self.scratch(len(column), column.dtype.type) for column in pair))  # type: ignore[arg-type]
        return self.pairs[1] if pair[0] is self.pairs[0][0] else self.pairs[0]

    @staticmethod
    def _in_memory(pair: tuple[np.ndarray, np.ndarray], a: int, b: int, bits: int) -> None:
        """Rows ``a..b`` of ``pair`` copied into memory, sorted there, and written back."""
        keys, order = (np.array(column[a:b]) for column in pair)
        for column in pair:
            release_rows(column[a:b])
        _kernels.radix_sort(keys, order, bits)
        for column, rows in zip(pair, (keys, order), strict=True):
            column[a:b] = rows
            release_rows(column[a:b])


def _copy(source: tuple[np.ndarray, ...], target: tuple[np.ndarray, ...], a: int, b: int) -> None:
    """Rows ``a..b`` of each of ``source`` copied into ``target``'s, a step at a time."""
    for column, into in zip(source, target, strict=True):
        for lo, step in in_steps(column[a:b]):
            rows = into[a + lo : a + lo + len(step)]
            rows[:] = step
            release_rows(rows)
