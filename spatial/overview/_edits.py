"""An overview's edits: ``insert`` and ``remove`` made copy-on-write (``copy()`` first), each
its own path through persistent maps, those folded into runs of arrays past ``FOLD_AFTER``
entries (``_folded``), and all of them saved and made again as arrays (``edits``,
``with_edits``).

A removed item is subtracted from its aggregate in every band; an added item joins the
tightest live aggregate whose box contains its box, or starts one of its own. Apart from the
reads (``_Reads``, which ``_Edits`` extends): an edit reads the aggregates it changes as any
read does, and nothing that only reads needs to know how edits are made.
"""

from __future__ import annotations

import functools
import math
from operator import itemgetter
from typing import Any, Self

import numpy as np
from immutables import Map

from ..quadtree import QuadTree
from ..rect import RectLike, as_rect
from ._folded import _DRAWN, _NOTHING_FOLDED, _ROW_TYPES, _Folded, _joined, _Rows
from ._reads import _Reads

__all__ = ["FOLD_AFTER"]

FOLD_AFTER = 2048  # entries of the maps of recent edits before they are folded into arrays


class _Edits(_Reads):
    """The edits of an overview since its build, each a copy-on-write path through its maps."""

    # -- edits -------------------------------------------------------------------------------

    def copy(self) -> Self:
        """An overview sharing the built bands and the maps of edits since (persistent: edits
        to one do not touch the other). Cost: O(1)."""
        clone = object.__new__(type(self))
        clone.__dict__.update(self.__dict__)
        clone._owned = set()
        return clone

    def edits(self) -> dict[str, Any]:
        """The edits since the build, as arrays (``with_edits`` makes them again over the same
        build): the aggregates changed or added, the items' new homes and each band's next
        index. Cost: O(what edits changed), in numpy but for the recent ones."""
        folded = functools.reduce(_Folded.updated, (*self._folded, self._maps_folded()), _NOTHING_FOLDED)
        bands = sorted(folded.rows)
        rows = [folded.rows[band] for band in bands]
        return {
            "at": np.column_stack(
                [
                    np.repeat(np.array(bands, np.int64), [len(r.indices) for r in rows]),
                    _joined(rows, "indices", (0,)),
                ]
            ).astype(np.int64),
            "box": _joined(rows, "box", (0, 4)),
            "count": _joined(rows, "counts", (0,)),
            "area": _joined(rows, "area", (0,)),
            "zkp": np.column_stack([_joined(rows, k, (0,)) for k in ("z", "kind", "parent")]).astype(
                np.int64
            ),
            "items": folded.items,
            "homes": np.column_stack([folded.level, folded.home]).astype(np.int64),
            "next": np.array(list(self._next.items()), np.int64).reshape(-1, 2),
        }

    def with_edits(self, edits: dict[str, Any]) -> Self:
        """A copy of this overview, as built (no edits), with ``edits`` (``edits()``) made
        again: held as they come, in arrays. Cost: O(what edits changed), in numpy, and the
        bands' trees' edits (``QuadTree.with_edits``).

        :raises ValueError: if ``edits`` do not fit it
        """
        if self._edited:
            raise ValueError("edits are made again over an overview as built, with none of its own")
        clone = self.copy()
        at, count, boxes = edits["at"].reshape(-1, 2), edits["count"], edits["box"].reshape(-1, 4)
        zkp, homes = edits["zkp"].reshape(-1, 3), edits["homes"].reshape(-1, 2)
        order = np.lexsort((at[:, 1], at[:, 0]))
        at, count, boxes, zkp, area = at[order], count[order], boxes[order], zkp[order], edits["area"][order]
        rows, trees = {}, {}
        for band in np.unique(at[:, 0]).tolist():
            lo, hi = np.searchsorted(at[:, 0], [band, band + 1])
            index = at[lo:hi, 1]
            rows[band] = _Rows(index, boxes[lo:hi], count[lo:hi], area[lo:hi], *zkp[lo:hi].T)
            # A band's tree holds its live aggregates: those emptied leave it, those added join
            # it (an aggregate's box never changes), in the order they were made
            new = index >= self.built(band)
            removed, added = index[~new & (count[lo:hi] == 0)], np.flatnonzero(new & (count[lo:hi] > 0))
            if len(removed) or len(added):  # room for twice as many before the tree rebuilds
                tree = self._tree(band)
                tree = QuadTree() if tree is None else tree
                room = np.array([max(tree.max_buffered, 2 * len(added))])
                trees[band] = tree.with_edits(
                    {
                        "removed": removed,
                        "ids": index[added],
                        "boxes": boxes[lo:hi][added],
                        "max_buffered": room,
                    }
                )
        items = edits["items"]
        order = np.argsort(items, kind="stable")
        clone._folded = (_Folded(rows, items[order], homes[order, 0], homes[order, 1]),)
        clone._next = Map(map(tuple, edits["next"].reshape(-1, 2).tolist()))
        clone._trees = Map(trees)
        return clone

    def _maps_folded(self) -> _Folded:
        """The maps of recent edits as a run of arrays."""
        recent: dict[int, list[tuple[int, tuple]]] = {}
        for (band, index), row in self._state.items():
            recent.setdefault(band, []).append((index, row))
        rows = {}
        for band, changed in recent.items():
            changed.sort(key=itemgetter(0))
            rows[band] = _Rows(
                np.array([index for index, _ in changed], np.int64),
                np.array([row[0] for _, row in changed], np.float64).reshape(-1, 4),
                *(np.array([row[k] for _, row in changed], t) for k, t in _ROW_TYPES),
            )
        items = np.fromiter(self._member.keys(), np.int64, len(self._member))
        homes = np.array([(_DRAWN, -1) if h is None else h for h in self._member.values()], np.int64)
        order = np.argsort(items, kind="stable")
        return _Folded(rows, items[order], *homes.reshape(-1, 2)[order].T)

    def _fold_maps(self) -> None:
        """Fold the maps of recent edits into a run of arrays once they hold ``FOLD_AFTER``
        entries, then each run into the one before while it holds a quarter of that one's or
        more: a few runs, growing 4x each, and each entry copied a few times a run it passes
        through, however many edits pile up (O(log edits) an edit, amortized)."""
        if len(self._state) + len(self._member) <= FOLD_AFTER:
            return
        runs = [*self._folded, self._maps_folded()]
        while len(runs) > 1 and 4 * runs[-1].size >= runs[-2].size:
            newer = runs.pop()
            runs[-1] = runs[-1].updated(newer)
        self._folded = tuple(runs)
        self._state, self._member = Map(), Map()

    def remove(self, item: int, box: RectLike) -> set[tuple[int, int]]:
        """Take ``item`` (whose box is ``box``) out of its aggregates; the ``(band, index)`` changed.

        :raises KeyError: if ``item`` is not in the overview
        """
        where = self._home(item)
        self._member = self._member.set(item, None)
        changed: set[tuple[int, int]] = set()
        if where is None:
            return changed
        area = _area(as_rect(box, "box"))
        level, index = where
        while level <= self.hi and index >= 0:
            b, count, total, z, kind, parent = self._row(level, index)
            self._state = self._state.set(
                (level, index), (b, count - 1, max(0.0, total - area), z, kind, parent)
            )
            if count - 1 == 0:
                self._edit_tree(level).remove(index)
            changed.add((level, index))
            level, index = level + 1, parent
        self._fold_maps()
        return changed

    def insert(self, item: int, box: RectLike, kind: int = 0, z: int = 0) -> set[tuple[int, int]]:
        """Add ``item`` with ``box``, ``kind`` and ``z`` (or move it there: ``remove`` first);
        the ``(band, index)`` changed or created."""
        rect = as_rect(box, "box")
        size = max(rect[2] - rect[0], rect[3] - rect[1])
        first = self.lo if not size > 0 else min(max(math.frexp(size)[1], self.lo), self.hi + 1)
        if not math.isfinite(size) or first > self.hi:
            self._member = self._member.set(item, None)
            self._fold_maps()
            return set()
        changed: set[tuple[int, int]] = set()
        area, child = _area(rect), None
        for level in range(first, self.hi + 1):
            home = self._container(level, rect)
            if home is not None:  # join it, and its parents up the bands
                self._join(level, home, area, z, changed)
                if child is not None:
                    self._set_parent(child, home)
                else:
                    self._member = self._member.set(item, (level, home))
                self._fold_maps()
                return changed
            index = self._next.get(level, self.built(level))
            self._next = self._next.set(level, index + 1)
            self._state = self._state.set((level, index), (rect, 1, area, int(z), int(kind), -1))
            self._edit_tree(level).insert(index, rect)
            changed.add((level, index))
            if child is not None:
                self._set_parent(child, index)
            else:
                self._member = self._member.set(item, (level, index))
            child = (level, index)
        self._fold_maps()
        return changed

    # -- internals ---------------------------------------------------------------------------

    def _edit_tree(self, band: int) -> QuadTree:
        if band not in self._owned:  # copy on the first write since this overview was made
            tree = self._tree(band)
            self._trees = self._trees.set(band, QuadTree() if tree is None else tree.copy())
            self._owned.add(band)
        return self._trees[band]

    def _container(self, band: int, rect: tuple[float, float, float, float]) -> int | None:
        """The live aggregate of ``band`` with the smallest box containing ``rect``, or None."""
        best, best_area = None, math.inf
        for index in self.query(band, rect).tolist():
            box, count = self._row(band, index)[:2]
            if count > 0 and _contains(box, rect) and _area(box) < best_area:
                best, best_area = index, _area(box)
        return best

    def _join(self, band: int, index: int, area: float, z: int, changed: set[tuple[int, int]]) -> None:
        level = band
        while level <= self.hi and index >= 0:
            box, count, total, top, kind, parent = self._row(level, index)
            self._state = self._state.set(
                (level, index), (box, count + 1, total + area, max(top, int(z)), kind, parent)
            )
            changed.add((level, index))
            level, index = level + 1, parent

    def _set_parent(self, child: tuple[int, int], parent: int) -> None:
        box, count, area, z, kind, _ = self._row(*child)
        self._state = self._state.set(child, (box, count, area, z, kind, parent))


def _area(box: tuple[float, ...]) -> float:
    area = (box[2] - box[0]) * (box[3] - box[1])  # Python floats overflow to inf, silently
    return area if math.isfinite(area) else 0.0


def _contains(outer: tuple[float, ...], inner: tuple[float, ...]) -> bool:
    return outer[0] <= inner[0] and outer[1] <= inner[1] and inner[2] <= outer[2] and inner[3] <= outer[3]
