"""Edits folded into runs of sorted arrays: the rows of a band's aggregates that edits changed
or added (``_Rows``), and a run of them with the items edits added, moved or removed and their
homes (``_Folded``).

An overview keeps its recent edits in persistent maps, a Python step each to read; past
``FOLD_AFTER`` entries it folds them into a run of these (``_edits``), so a read of many
aggregates or items is a search of each run (``_reads``). A module of their own: the reads
and the edits both use them, and they need nothing of either.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, NamedTuple

import numpy as np

from ..sorting import found_in

__all__: list[str] = []  # the package's own: the reads and the edits use its ``_`` names

_ROW_TYPES = ((1, np.int64), (2, np.float64), (3, np.int64), (4, np.int64), (5, np.int64))  # count..parent


class _Rows(NamedTuple):
    """A band's aggregates edits changed or added, by index (sorted), as arrays: what a row of
    ``Overview._state`` holds, a column each."""

    indices: np.ndarray
    box: np.ndarray
    counts: np.ndarray
    area: np.ndarray
    z: np.ndarray
    kind: np.ndarray
    parent: np.ndarray

    def row(self, at: int) -> tuple:
        """Entry ``at`` as ``Overview._state`` holds a row."""
        return _row_at(at, *self[1:])

    def find(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each of ``indices`` is here, for those that are (``found_in``)."""
        return found_in(self.indices, indices)

    def updated(self, new: _Rows) -> _Rows:
        """These rows with ``new``'s, which replace those of the same index."""
        keep = ~np.isin(self.indices, new.indices)
        joined = [np.concatenate([mine[keep], theirs]) for mine, theirs in zip(self, new, strict=True)]
        order = np.argsort(joined[0], kind="stable")
        return _Rows(*(column[order] for column in joined))


def _found_one(keys: np.ndarray, key: int) -> int | None:
    """Where ``key`` is in ``keys`` (sorted), or None: ``found_in`` of one, without its arrays."""
    at = int(np.searchsorted(keys, key))
    return at if at < len(keys) and keys[at] == key else None


def _held(
    indices: np.ndarray, size: int, keys: Callable[[], Iterable[int]], holds: Callable[[int], bool]
) -> np.ndarray:
    """Which of ``indices`` a map of ``size`` entries holds: its ``keys`` read, or each looked
    up in it (``holds``), whichever are fewer (a Python step each)."""
    if not size or not len(indices):
        return np.zeros(len(indices), bool)
    if size <= len(indices):
        return np.isin(indices, np.fromiter(keys(), np.int64))
    return np.fromiter(map(holds, indices.tolist()), bool, len(indices))


def _row_at(at: int, box: Any, count: Any, area: Any, z: Any, kind: Any, parent: Any) -> tuple:
    """Row ``at`` of these columns (a band's as built, or edits folded), as
    ``Overview._state`` holds a row: ``(box, count, area, z, kind, parent)``."""
    return (
        tuple(box[at].tolist()),
        int(count[at]),
        float(area[at]),
        int(z[at]),
        int(kind[at]),
        int(parent[at]),
    )


class _Folded(NamedTuple):
    """Edits folded into arrays: each band's rows changed or added (``rows``), and the items
    edits added, moved or removed, sorted, with their homes (``level`` and ``home``, the
    aggregate there; ``level`` ``_DRAWN``: drawn themselves)."""

    rows: dict[int, _Rows]
    items: np.ndarray
    level: np.ndarray
    home: np.ndarray

    @property
    def size(self) -> int:
        return sum(len(rows.indices) for rows in self.rows.values()) + len(self.items)

    def updated(self, newer: _Folded) -> _Folded:
        """These edits with ``newer``'s, which replace those of the same aggregate or item."""
        rows = dict(self.rows)
        for band, theirs in newer.rows.items():
            rows[band] = theirs if band not in rows else rows[band].updated(theirs)
        keep = ~np.isin(self.items, newer.items)
        joined = [
            np.concatenate([mine[keep], theirs]) for mine, theirs in zip(self[1:], newer[1:], strict=True)
        ]
        order = np.argsort(joined[0], kind="stable")
        return _Folded(rows, *(column[order] for column in joined))


_DRAWN = np.iinfo(np.int64).min  # the level of an item drawn itself in every band: none is (bands go below 0)
_NOTHING_FOLDED = _Folded({}, *(np.empty(0, np.int64) for _ in range(3)))


def _joined(rows: list[_Rows], column: str, shape: tuple[int, ...]) -> np.ndarray:
    """``column`` of each of ``rows``, end to end (empty, of ``shape``, when none)."""
    parts = [getattr(r, column) for r in rows]
    return np.concatenate(parts) if parts else np.empty(shape)
