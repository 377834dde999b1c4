"""Overview: aggregates that stand in for items too small to draw, one set per zoom band.

Band ``L`` holds every item whose size ``max(w, h)`` is under ``2**L`` units, merged into
aggregate boxes; an item of that size or more is drawn itself. A client at ``min_size`` units
per drawable item takes band ``L = ceil(log2(min_size))``: the items of at least ``2**L``, plus
band L's aggregates for the rest, and nothing is left out.

How a band is built (bottom-up, so each band costs what it merges, not all items):

- Its elements are the previous band's aggregates plus the items that just became too small.
- Elements are filed by the cell of size ``2**L`` (about a pixel at that zoom) their centre is
  in. In each row of cells, a run of occupied cells with no empty cell between is one group;
  runs of the same columns in consecutive rows merge into one rectangle. Words along a line
  become line runs, lines become blocks, blocks become page silhouettes, and a whiteboard's
  clusters become stacks of slabs that follow their outline at cell resolution.
- An aggregate's box is the union of its elements' boxes (so it contains every member's box),
  its ``count`` the members, its ``cover`` the members' summed area over its box's area (at
  most 1), its ``kind`` that of its largest element by covered area, its ``z`` the highest.

Edits are incremental and copy-on-write (``copy()`` then ``insert``/``remove``): a removed item
is subtracted from its aggregate in every band; an added item joins the tightest aggregate whose
box contains its box, or starts one of its own. Boxes never shrink until the next build, so
every member stays inside its aggregate and every band's counts add up to its members.

The parts, a module each: ``_build`` (the builds, under the four grouping rules, a step at a
time), ``_reads`` (what an overview is made of, and every read of it: queries, rows, homes,
masks), ``_edits`` (the copy-on-write edits) and ``_folded`` (the runs of arrays edits are
folded into). ``Overview``, here, is the reads and the edits with how an overview is made:
built (``build``, ``build_arrays``), saved (``to_arrays``) and opened (``from_arrays``).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..budget import MemoryBudget, current
from ..paging import Scratch, bounds, release
from ..quadtree import QuadTree, ReadWatch
from ..rect import as_box_array
from ._build import RULES, _Band, _band_arrays, _first_bands, _least_size, _levels, _merged, _TreeBoxes
from ._build import TILE as TILE  # the most cells an aggregate spans a side (its mask's bound)
from ._edits import _contains, _Edits
from ._reads import Aggregate, _CheckedBands, band_for_size

__all__ = ["Aggregate", "Overview", "RULES", "band_for_size"]


class Overview(_Edits):
    """Aggregates per band over a set of items (by position ``0..n-1``), with incremental edits.

    >>> boxes = [[0, 0, 4, 2], [5, 0, 9, 2], [0, 3, 9, 5], [100, 100, 300, 300]]
    >>> view = Overview.build(boxes, kinds=[1, 1, 1, 0], z=[3, 3, 3, 0])
    >>> view.band(200.0)   # at 200 units a drawable item, band 8 (256 units)
    8
    >>> [view.get(8, k).count for k in view.query(8, (0, 0, 1000, 1000)).tolist()]
    [4]
    >>> [view.get(4, k).box for k in view.query(4, (0, 0, 1000, 1000)).tolist()]
    [(0.0, 0.0, 9.0, 5.0)]
    """

    @classmethod
    def build(
        cls, boxes: object, kinds: object = None, z: object = None, *, rule: str = "rectangles"
    ) -> Overview:
        """Aggregates of ``boxes`` (n, 4) in every band, with ``kinds`` and ``z`` (n,) integers.

        ``rule`` says which occupied cells of a band make one aggregate: ``"rectangles"`` (runs
        of a row, and the runs over the same columns in consecutive rows), ``"rows"`` (runs of
        a row), ``"cells"`` (each cell), ``"blobs"`` (runs, and runs overlapping in consecutive
        rows). The default draws closest to the items per aggregate (docs/TRADEOFFS.md).

        Cost: O(n log n) over the bands an item is merged in (~0.6 s for a million word boxes).

        :raises ValueError: if a box is not finite or inverted, the columns' lengths differ, or
            ``rule`` is not one of those
        """
        view, bands = cls._building(boxes, kinds, z, rule)
        for level, band in bands:
            view._bands[level] = band
        return view

    @classmethod
    def build_arrays(
        cls,
        boxes: object,
        kinds: object = None,
        z: object = None,
        *,
        rule: str = "rectangles",
        homes: np.ndarray | None = None,
        scratch: Scratch | None = None,
        budget: MemoryBudget | None = None,
    ) -> Iterator[tuple[str, np.ndarray]]:
        """``build(...).to_arrays()``'s arrays, each yielded once it is final (a band's once
        the band above is merged from it), to be written and let go: the build then holds a
        band's elements and the band below, never every band. ``homes``: an int32 array of
        one an item to make the items' homes in (one mapped from a file, shared: its pages
        are handed back after each band's writes), yielded as ``"homes"``. ``scratch``: makes
        arrays in files; the band below's boxes and columns are copied there while the next
        band is merged, a step at a time (~52 bytes an aggregate less), its windows of
        ``budget`` (None: the budget held at this call, ``budget.current()``), held while the
        build runs, not between the arrays it yields.

        :raises ValueError: as ``build``, before the first is yielded
        """
        return _each_held(budget or current(), cls._arrays(boxes, kinds, z, rule, homes, scratch))

    @classmethod
    def _arrays(
        cls,
        boxes: object,
        kinds: object,
        z: object,
        rule: str,
        homes: np.ndarray | None,
        scratch: Scratch | None,
    ) -> Iterator[tuple[str, np.ndarray]]:
        view, bands = cls._building(boxes, kinds, z, rule, homes, scratch)
        below: tuple[str, np.ndarray] | None = None  # the last band's parents: final at the next
        for level, band in bands:
            if below is not None:
                yield below
            arrays = _band_arrays(level, band)
            del band
            below = (f"{level}.parent", arrays.pop(f"{level}.parent"))
            while arrays:
                yield arrays.popitem()
        if below is not None:
            yield below
        yield from view._top_arrays().items()

    @classmethod
    def _building(
        cls,
        boxes: object,
        kinds: object,
        z: object,
        rule: str,
        homes: np.ndarray | None = None,
        scratch: Scratch | None = None,
    ) -> tuple[Overview, Iterator[tuple[int, _Band]]]:
        """An overview with no bands yet, and its bands, each as soon as it is merged (its
        ``parent`` is filled in place when the band above is merged from it); the items' homes
        are complete when the bands are all made."""
        if rule not in RULES:
            raise ValueError(f"rule must be one of {', '.join(RULES)}; got {rule!r}")
        boxes = as_box_array(boxes)
        n = len(boxes)
        kinds = np.zeros(n, np.int32) if kinds is None else np.asarray(kinds, np.int32)
        z = np.zeros(n, np.int32) if z is None else np.asarray(z, np.int32)
        if kinds.shape != (n,) or z.shape != (n,):
            raise ValueError(
                f"kinds and z must hold one value per box ({n}), got {kinds.shape} and {z.shape}"
            )
        extent = bounds(boxes)
        lo, hi = _levels(extent, _least_size(boxes)) if n else (0, -1)
        view = cls(lo, hi)
        if homes is None:
            homes = np.full(n, -1, np.int32)  # the bands hold under 2**31 aggregates
        elif homes.shape == (n,) and homes.dtype == np.int32:
            homes.fill(-1)
            release(homes)
        else:
            raise ValueError(f"homes must be int32, one an item ({n}): got {homes.dtype} {homes.shape}")
        view._homes = homes
        if n == 0:
            return view, iter(())
        first = _first_bands(boxes, lo, hi, scratch)
        return view, _merged(view, boxes, kinds, z, rule, first, extent[:2], scratch)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The built overview as named arrays (``from_arrays`` takes them back), to save it.

        :raises ValueError: if edits were made since the build (save a fresh build instead)
        """
        if self._edited or self._trees:
            raise ValueError("an overview with edits since its build cannot be saved; build it anew")
        out = self._top_arrays()
        for level, band in self._bands.items():
            out.update(_band_arrays(level, band))
        return out

    def _top_arrays(self) -> dict[str, np.ndarray]:
        """The arrays of ``to_arrays`` that are not a band's."""
        return {
            "levels": np.array([self.lo, self.hi], np.int64),
            "homes": self._homes,
            "starts": self._starts,
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], watch: ReadWatch | None = None) -> Overview:
        """An overview from ``to_arrays``' arrays, used as they are (a mapped file's, say).
        With ``watch``, each band's arrays, and the items' homes, are checked by it on their
        first use (see ``QuadTree.from_arrays``).

        :raises ValueError: if the arrays do not make an overview
        """
        try:
            lo, hi = (int(v) for v in arrays["levels"])
            view = cls(lo, hi)
            view._homes, view._starts = arrays["homes"], arrays["starts"]
            if watch is not None:
                view._bands, view._watch = _CheckedBands(watch), watch
            for level in {
                int(name.split(".")[0]) for name in arrays if name.split(".")[0].lstrip("-").isdigit()
            }:
                fields = {n: arrays[f"{level}.{n}"] for n in ("count", "area", "z", "kind", "parent")}
                prefix = f"{level}.tree."
                under = {k[len(prefix) :]: v for k, v in arrays.items() if k.startswith(prefix)}
                tree, slot = QuadTree.from_arrays(under, watch), arrays[f"{level}.slot"]
                if not len(slot) == len(tree) == len(fields["count"]) or under["boxes"].dtype != np.float64:
                    raise ValueError(
                        f"band {level}: {len(slot)} aggregates, {len(fields['count'])} counts, a tree of "
                        f"{len(tree)} with {under['boxes'].dtype} boxes (float64 expected)"
                    )
                tree.locate_by(slot)  # an edit's removal reads the slot it needs, not every id
                view._bands[level] = _Band(_TreeBoxes(under["boxes"], slot), **fields, tree=tree)
        except KeyError as missing:
            raise ValueError(f"not an overview's arrays: {missing} is missing") from None
        return view

    # -- invariants --------------------------------------------------------------------------

    def _check(self, boxes: dict[int, tuple[float, float, float, float]]) -> None:
        """Assert the invariants against ``boxes``, every live item's box by position: each item
        under ``2**L`` is in a live aggregate of band L containing its box, each band's counts
        add up to its members, and a parent contains its children."""
        for level in range(self.lo, self.hi + 1):
            members = {item for item, box in boxes.items() if _size(box) < self.threshold(level)}
            total = sum(int(c) for c in self.rows(level, self.query(level, _everything()))[1])
            assert total == len(members), f"band {level}: counts add to {total}, not {len(members)}"
            for item in members:
                index = self.aggregate_of(item, level)
                assert index is not None, f"item {item} has no aggregate in band {level}"
                agg = self.get(level, index)
                assert _contains(agg.box, boxes[item]), (
                    f"item {item} is outside its aggregate in band {level}"
                )


def _size(box: tuple[float, ...]) -> float:
    return max(box[2] - box[0], box[3] - box[1])


def _everything() -> tuple[float, float, float, float]:
    big = np.finfo(np.float64).max
    return (-big, -big, big, big)


def _each_held(
    budget: MemoryBudget, steps: Iterator[tuple[str, np.ndarray]]
) -> Iterator[tuple[str, np.ndarray]]:
    """``steps``, each made with ``budget`` held (and not while the caller writes it)."""
    while True:
        with budget.held():
            step = next(steps, None)
        if step is None:
            return
        yield step
        del step  # let go once written, before the next is made
