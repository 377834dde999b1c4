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
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from operator import itemgetter
from typing import Any, NamedTuple

import numpy as np
from immutables import Map

from . import _kernels, _paging
from ._paging import (
    Scratch,
    bounds,
    filled,
    in_file,
    in_steps,
    new_array,
    placed,
    release,
    release_rows,
    steps,
    steps_at,
    windows,
)
from ._sorting import found_in, sorted_keys
from .quadtree import QuadTree, ReadWatch
from .raster import occupancy
from .rect import RectLike, as_box_array, as_rect

__all__ = ["Aggregate", "Overview", "RULES", "band_for_size"]

RULES = ("rectangles", "rows", "cells", "blobs")  # how occupied cells make aggregates: see build()
_SPAN = 52  # bands below the top one at most: cells finer than float spacing tell nothing apart
# An aggregate spans at most TILE x TILE cells of its band: tiles aligned on the band's grid cut
# the groups, so an aggregate's shape (its mask, drawn pixel for pixel) stays a bounded size.
TILE = 8
_NONE = np.empty(0, np.int64)


class Aggregate(NamedTuple):
    """One aggregate: its box, how many items it stands for, and how it looks."""

    box: tuple[float, float, float, float]
    count: int  # type: ignore[assignment]  # shadows tuple.count, a public field name since the start
    cover: float  # members' summed area over the box's area, at most 1
    kind: int  # the kind code of its largest element by area
    z: int  # the highest z among its members


def band_for_size(min_size: float) -> int:
    """The smallest ``L`` with ``2**L >= min_size`` (``min_size`` > 0), exactly.

    >>> band_for_size(1.0), band_for_size(1.5), band_for_size(2.0), band_for_size(0.3)
    (0, 1, 1, -1)
    """
    mantissa, exponent = math.frexp(min_size)
    return exponent - 1 if mantissa == 0.5 else exponent


@dataclass
class _Band:
    """One band's aggregates, by index: the built arrays are never modified once built."""

    boxes: _TreeBoxes  # (a, 4) float64, read from its tree's
    count: np.ndarray  # (a,) int32
    area: np.ndarray  # (a,) float64, the members' summed area
    z: np.ndarray  # (a,) int32
    kind: np.ndarray  # (a,) int32
    parent: np.ndarray  # (a,) int32: index in the next band (-1 at the top)
    tree: QuadTree

    def arrays(self) -> tuple[np.ndarray, ...]:
        """The arrays its aggregates are read from (its tree aside)."""
        return (*self.boxes.arrays(), self.count, self.area, self.z, self.kind, self.parent)

    def columns(self) -> tuple[np.ndarray, ...]:
        """``_Below``'s columns but the boxes."""
        return self.area, self.count, self.z, self.kind, self.parent


@dataclass
class _Below:
    """What a band's merge reads of the band below: its aggregates' boxes (gathered in their
    order) and columns, ``parent`` filled in by the merge."""

    boxes: np.ndarray
    area: np.ndarray
    count: np.ndarray
    z: np.ndarray
    kind: np.ndarray
    parent: np.ndarray


def _below(band: _Band, scratch: Scratch | None) -> _Below:
    """What the band above merges of ``band``: its boxes gathered in its aggregates' order, and
    its columns (with ``scratch``, in files already, as ``_merge`` makes them); with
    ``scratch``, the boxes gathered into a file a step at a time, so the band's tree can go
    once written."""
    boxes, slot = band.boxes.arrays()
    gathered = new_array(scratch, 4 * len(slot), np.float64).reshape(-1, 4)
    for lo, hi in steps(len(slot), 32):
        np.take(boxes, slot[lo:hi], axis=0, out=gathered[lo:hi])
        for array in (gathered, slot):
            release_rows(array[lo:hi])
        release(boxes)  # read at random (mapped: the band's, in a file)
    return _Below(gathered, *band.columns())


class _TreeBoxes:
    """The boxes of a band, read from its tree's: each box is kept once, there (28 B an
    aggregate less, in memory and on disk). Aggregate ``k``'s is ``boxes[slot[k]]``."""

    __slots__ = ("boxes", "slot")

    def __init__(self, boxes: np.ndarray, slot: np.ndarray) -> None:
        self.boxes, self.slot = boxes, slot

    @classmethod
    def of(cls, tree: QuadTree, scratch: Scratch | None = None) -> _TreeBoxes:
        """The boxes ``tree`` was built over, in their order (``tree``'s ids); with
        ``scratch``, their slots made in a file."""
        arrays = tree.to_arrays()
        # a band holds under 2**31 aggregates
        return cls(arrays["boxes"], placed(arrays["ids"], new_array(scratch, len(arrays["ids"]), np.int32)))

    def __getitem__(self, index: Any) -> np.ndarray:
        return self.boxes[self.slot[index]]

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return self.boxes, self.slot


class Overview:
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

    def __init__(self, lo: int, hi: int) -> None:
        self.lo, self.hi = lo, hi  # bands lo..hi; none when hi < lo (no items)
        self._bands: dict[int, _Band] = {}
        # Each built item's home: its aggregate in its first band, numbered across the bands
        # (band lo's first, then the next's: 4 bytes an item where a band and an index took 6),
        # -1 for an item drawn itself in every band; ``_starts[b]``: band lo + b's first number
        self._homes = np.empty(0, np.int32)
        self._starts = np.zeros(1, np.int64)
        # Edits since the build, in persistent maps (a copy shares them; each edit makes its
        # own path): changed or new aggregates' (box, count, area, z, kind, parent); trees that
        # gained or lost aggregates; the next index per band; items added or moved ((band,
        # index), or None: drawn themselves).
        self._state: Map[tuple[int, int], tuple] = Map()
        self._trees: Map[int, QuadTree] = Map()
        self._next: Map[int, int] = Map()
        self._member: Map[int, tuple[int, int] | None] = Map()
        # The edits of the two maps above, past ``FOLD_AFTER`` entries, folded into runs of
        # sorted arrays, oldest first (the maps then hold those since; a newer run's entry
        # replaces an older's): a read of many aggregates or items is a search of each run,
        # not a Python step each, and an open takes them from a file as they are
        self._folded: tuple[_Folded, ...] = ()
        self._owned: set[int] = set()  # bands whose tree this overview copied and may edit in place
        self._watch: ReadWatch | None = None  # checks the homes (first, agg) mapped from a file

    def _read_homes(self) -> None:
        """Before the items' homes are read: every block of them checked, the first time."""
        if self._watch is not None:
            self._watch.check(self._homes)
            self._watch = None  # in this overview and the copies made from now on

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
    ) -> Iterator[tuple[str, np.ndarray]]:
        """``build(...).to_arrays()``'s arrays, each yielded once it is final (a band's once
        the band above is merged from it), to be written and let go: the build then holds a
        band's elements and the band below, never every band. ``homes``: an int32 array of
        one an item to make the items' homes in (one mapped from a file, shared: its pages
        are handed back after each band's writes), yielded as ``"homes"``. ``scratch``: makes
        arrays in files; the band below's boxes and columns are copied there while the next
        band is merged, a step at a time (~52 bytes an aggregate less).

        :raises ValueError: as ``build``, before the first is yielded
        """
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
        return view, view._merged(boxes, kinds, z, rule, first, extent[:2], scratch)

    def _merged(
        self,
        boxes: np.ndarray,
        kinds: np.ndarray,
        z: np.ndarray,
        rule: str,
        first: np.ndarray,
        origin: tuple[float, float],
        scratch: Scratch | None,
    ) -> Iterator[tuple[int, _Band]]:
        """The bands merged from the items, ``first`` each one's first band; see ``_building``.
        The build holds a few columns at a time: its peak ~14 bytes an item above its input
        on a board, built as an import builds it, with ``scratch`` (``tests/test_build_memory.py``)."""
        lo, hi = self.lo, self.hi
        # Each band's new items found by a pass over ``first`` (2 bytes an item) where any are,
        # not by holding an argsort of it (8 bytes an item, through the build's peak)
        joining = np.zeros(hi - lo + 2, np.int64)
        for _, step in in_steps(first):
            joining += np.bincount(step - lo, minlength=hi - lo + 2)
        ox, oy = origin
        previous: _Below | None = None
        held = []
        for level in range(lo, hi + 1):
            new = _joining(first, level, int(joining[level - lo]), scratch)
            if previous is None and not len(new):
                held.append(0)
                continue
            elements = _elements(previous, boxes, new, z, kinds)
            parent = None if previous is None else previous.parent
            previous = None  # in the elements now
            band, owner = _merge(level, ox, oy, rule, elements, scratch)  # it lets them go once reduced
            if parent is not None:  # a step at a time: both mapped, their pages handed back
                for at, step in in_steps(owner[: len(parent)]):
                    into = parent[at : at + len(step)]
                    into[:] = step
                    release_rows(into)
            # The items' homes, numbered within the band for now: a step of them at a time
            # (``new`` ascends), each step's pages written handed back (mapped from a file)
            joined = len(owner) - len(new)
            for a, b in _stepped(self._homes, new):
                self._homes[new[a:b]] = owner[joined + a : joined + b]
            release(owner)  # read in order: mapped, its pages handed back
            del owner
            held.append(len(band.count))
            # What the band above merges of it, its boxes gathered in its aggregates' order
            # before it is handed over: its tree (the boxes in its order) can then go once
            # written, never held beside the gathered copy and the next band's columns
            previous = _below(band, scratch)
            yield level, band
            del band
        self._starts = np.concatenate((np.zeros(1, np.int64), np.cumsum(held, dtype=np.int64)))
        starts = self._starts.astype(np.int32)  # numbered across the bands: under 2**31
        for at, step in in_steps(self._homes):  # a step's pages handed back after it
            firsts = first[at : at + len(step)]
            home = firsts <= hi
            step[home] += starts[firsts[home] - lo]
            release_rows(firsts)

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

    # -- queries -----------------------------------------------------------------------------

    def band(self, min_size: float) -> int | None:
        """The band for a client drawing items of at least ``min_size`` units: ``ceil(log2)``,
        clamped to the bands there are; None when there are none (no items) or ``min_size`` is 0.
        Items of ``2**band`` units or more are drawn themselves; the band's aggregates stand in
        for the rest."""
        if not min_size > 0 or self.hi < self.lo:
            return None
        return min(max(band_for_size(min_size), self.lo), self.hi)

    def band_within(self, tree: QuadTree, rect: RectLike, min_size: float, most: float) -> int | None:
        """The band for ``rect`` at ``min_size`` (see ``band``), or a coarser one while the items
        of ``tree`` drawn themselves plus the band's aggregates touching ``rect`` are more than
        ``most``: what an answer within a budget of entries shows. ``tree`` holds the same items.
        Cost: two queries per band tried."""
        choice = self.choose(tree, rect, min_size, most)
        return None if choice is None else choice[0]

    def choose(
        self, tree: QuadTree, rect: RectLike, min_size: float, most: float
    ) -> tuple[int, np.ndarray, np.ndarray] | None:
        """``band_within``'s band, with what it shows: the items of ``tree`` drawn themselves
        and the band's aggregates touching ``rect`` (the queries that chose it, which an answer
        would otherwise run again); None when ``min_size`` needs no band."""
        band = self.band(min_size)
        if band is None:
            return None
        while True:
            drawn, aggregates = tree.query(rect, min_size=self.threshold(band)), self.query(band, rect)
            if band >= self.hi or len(drawn) + len(aggregates) <= most:
                return band, drawn, aggregates
            band += 1

    @staticmethod
    def threshold(band: int) -> float:
        """Items at least this big are drawn themselves at ``band``: ``2**band`` units."""
        return math.ldexp(1.0, band)

    def query(self, band: int, rect: RectLike) -> np.ndarray:
        """Indices of ``band``'s aggregates whose box touches ``rect``. Cost: a tree query."""
        tree = self._tree(band)
        return _NONE if tree is None else tree.query(rect)

    def diff(self, band: int, old: RectLike, new: RectLike) -> tuple[np.ndarray, np.ndarray]:
        """``(entered, left)`` aggregates of ``band`` from viewport ``old`` to ``new``."""
        tree = self._tree(band)
        return (_NONE, _NONE) if tree is None else tree.diff(old, new)

    def get(self, band: int, index: int) -> Aggregate:
        """Aggregate ``index`` of ``band``.

        :raises KeyError: if there is no such aggregate (or it lost its last member)
        """
        box, count, area, z, kind, _ = self._row(band, index)
        if count <= 0:
            raise KeyError(f"aggregate {index} of band {band} has no members")
        w, h = box[2] - box[0], box[3] - box[1]
        cover = min(1.0, area / (w * h)) if w * h > 0 else 1.0
        return Aggregate(box, count, cover, kind, z)

    def built(self, band: int) -> int:
        """How many aggregates ``band`` was built with (edits add more after them)."""
        built = dict.get(self._bands, band)  # its length alone: nothing of it read
        return 0 if built is None else len(built.count)

    def edited(self, band: int, indices: np.ndarray) -> np.ndarray:
        """Which of ``band``'s aggregates at ``indices`` edits changed or added since the build,
        a bool each. Cost: a search of the folded edits, and the recent ones looked up."""
        indices = np.asarray(indices, np.int64)
        out = self._recent_among(band, indices)
        for run in self._folded:
            rows = run.rows.get(band)
            if rows is not None and len(indices):
                out |= rows.find(indices)[1]
        return out

    def _recent_among(self, band: int, indices: np.ndarray) -> np.ndarray:
        """Which of ``band``'s aggregates at ``indices`` the map of recent edits holds."""
        state = self._state
        return _held(
            indices, len(state), lambda: (k for b, k in state if b == band), lambda k: (band, k) in state
        )

    @property
    def _edited(self) -> bool:
        return bool(self._state or self._member or self._folded)

    def boxes(self, band: int, indices: np.ndarray) -> np.ndarray:
        """The boxes of ``band``'s aggregates at ``indices``, (n, 4): ``rows``' first column,
        alone (a mask reads hundreds of thousands)."""
        idx = np.asarray(indices, np.int64)
        built = self._bands.get(band)
        size = 0 if built is None else len(built.count)
        if built is not None and not self._edits_in(band) and (not len(idx) or idx.max() < size):
            return built.boxes[idx]
        return self.rows(band, idx)[0]

    def rows(
        self, band: int, indices: np.ndarray, *, as_built: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(boxes, count, cover, kind, z)`` of ``band``'s aggregates at ``indices``, as arrays;
        with ``as_built``, as they were built (indices below ``built(band)``), edits aside.
        Cost: O(len(indices)) in numpy, plus a Python step per aggregate an edit changed."""
        idx = np.asarray(indices, np.int64)
        built = self._bands.get(band)
        size = 0 if built is None else len(built.count)
        safe = np.where(idx < size, idx, 0)
        if built is not None and size:
            out = [built.boxes[safe], built.count[safe], built.area[safe], built.kind[safe], built.z[safe]]
        else:
            out = [
                np.empty((len(idx), 4)),
                *(np.empty(len(idx), t) for t in (np.int64, float, np.int64, np.int64)),
            ]
        if self._edits_in(band) and not as_built:  # edited or new aggregates come from the edits
            found = idx < size
            for folded in (run.rows[band] for run in self._folded if band in run.rows):  # oldest first
                at, hit = folded.find(idx)
                out[0][hit], out[1][hit], out[2][hit] = folded.box[at], folded.counts[at], folded.area[at]
                out[3][hit], out[4][hit] = folded.kind[at], folded.z[at]
                found |= hit
            for i in np.flatnonzero(self._recent_among(band, idx)).tolist():
                box, count, area, z, kind, _ = self._state[(band, int(idx[i]))]
                out[0][i], out[1][i], out[2][i], out[3][i], out[4][i] = box, count, area, kind, z
                found[i] = True
            if not found.all():
                raise KeyError(f"no aggregate {int(idx[np.argmin(found)])} in band {band}")
        boxes, count, area, kind, z = out
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            w, h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
            cover = np.where(w * h > 0, np.minimum(1.0, area / (w * h)), 1.0)
        return boxes, count, cover, kind, z

    def aggregate_of(self, item: int, band: int) -> int | None:
        """The aggregate of ``band`` that ``item`` belongs to; None when it is drawn itself there.

        :raises KeyError: if ``item`` is not in the overview
        """
        where = self._home(item)
        if where is None or where[0] > band:
            return None
        level, index = where
        while level < band:
            index = self._row(level, index)[5]
            level += 1
        return index

    def ancestors(self, level: int, indices: np.ndarray, band: int) -> np.ndarray:
        """The aggregate of ``band`` (``>= level``) each of ``level``'s aggregates at ``indices``
        belongs to (-1 for -1). Cost: a gather per band between, plus a Python step per
        aggregate an edit changed."""
        out = np.asarray(indices, np.int64).copy()
        for at in range(level, band):
            built = self._bands.get(at)
            size = 0 if built is None else len(built.parent)
            up = np.full(len(out), -1, np.int64)
            inside = (out >= 0) & (out < size)
            if built is not None:
                up[inside] = built.parent[out[inside]]
            if self._edits_in(at):  # changed or new aggregates: their parent as the edits left it
                for folded in (run.rows[at] for run in self._folded if at in run.rows):  # oldest first
                    where, hit = folded.find(out)
                    up[hit] = folded.parent[where]
                for i in np.flatnonzero(self._recent_among(at, out) & (out >= 0)).tolist():
                    up[i] = self._state[(at, int(out[i]))][5]
            out = up
        return out

    def homes(self, items: np.ndarray, band: int) -> np.ndarray:
        """The aggregate of ``band`` each of ``items`` belongs to; -1 where the item is drawn
        itself there. Vectorised :meth:`aggregate_of`, for many items at once.

        :raises KeyError: if an item is not in the overview
        """
        items = np.asarray(items, np.int64)
        first = np.full(len(items), self.hi + 1, np.int64)
        agg = np.full(len(items), -1, np.int64)
        built = items < len(self._homes)
        self._read_homes()
        first[built], agg[built] = self._split(self._homes[items[built]])
        moved = ~built
        for run in self._folded:  # items edits added, moved or removed, folded (oldest first)
            at, hit = found_in(run.items, items)
            level, index = run.level[at], run.home[at]
            first[hit] = np.where(level == _DRAWN, self.hi + 1, level)
            agg[hit] = np.where(level == _DRAWN, -1, index)
            moved &= ~hit
        member = self._member  # ... and since
        moved |= _held(items, len(member), member.keys, member.__contains__)
        for i in np.flatnonzero(moved).tolist():
            home = self._home(int(items[i]))
            first[i], agg[i] = (self.hi + 1, -1) if home is None else home
        out = np.full(len(items), -1, np.int64)
        for level in np.unique(first[first <= band]).tolist():
            at = first == level
            out[at] = self.ancestors(level, agg[at], band)
        return out

    def masks(
        self,
        band: int,
        aggregates: np.ndarray,
        origin: tuple[float, float],
        scale: float,
        tree: QuadTree,
        boxes_of: Callable[[np.ndarray], np.ndarray],
        most: int = 1 << 22,
        slack: float = 0.0,
        total: int | None = None,
    ) -> tuple[list[tuple[int, int, int, int]], list[np.ndarray]]:
        """Which pixels of a grid (``scale`` pixels a unit, pixel (0, 0) at ``origin``) each of
        ``band``'s ``aggregates`` has members touching: per aggregate, its box's window of
        pixels ``(c0, r0, w, h)`` and a (h, w) bool array (see :func:`spatial.raster.occupancy`).
        ``tree`` holds the items (by the positions this overview knows them by) and
        ``boxes_of(positions)`` gives their boxes. An aggregate covering more than ``most``
        pixels gets none (an empty window), as do those past ``total`` pixels together;
        ``slack``: see :func:`spatial.raster.occupancy`.

        The members are not read one by one: the aggregates of the band whose cells are under a
        pixel stand in for the items under that size (each is within a cell of its members),
        and the items between that size and ``band``'s threshold are read themselves. Cost:
        what that band and the tree hold around the aggregates, then one compiled pass."""
        boxes = self.boxes(band, aggregates)
        finer = min(max(band_for_size(1.0 / scale) - 1, self.lo), band)  # cells under a pixel
        if finer == band or not len(aggregates):  # the aggregates are fine enough themselves
            return occupancy(boxes, np.arange(len(aggregates)), boxes, origin, scale, most, slack, total)
        region = (
            float(boxes[:, 0].min()),
            float(boxes[:, 1].min()),
            float(boxes[:, 2].max()),
            float(boxes[:, 3].max()),
        )
        parts = self.query(finer, region)
        items = tree.query(region, min_size=self.threshold(finer))
        item_boxes = boxes_of(items)
        small = _sizes(item_boxes) < self.threshold(band)
        members = np.concatenate([self.boxes(finer, parts), item_boxes[small]])
        owners = np.concatenate([self.ancestors(finer, parts, band), self.homes(items[small], band)])
        # each member's place in ``aggregates`` (-1: another aggregate's, or drawn itself)
        slot = np.full(max(int(aggregates.max()), int(owners.max(initial=-1))) + 2, -1, np.int64)
        slot[aggregates] = np.arange(len(aggregates))
        place = slot[owners]  # an owner of -1 reads the last slot, which is -1
        mine = place >= 0
        return occupancy(members[mine], place[mine], boxes, origin, scale, most, slack, total)

    # -- edits -------------------------------------------------------------------------------

    def copy(self) -> Overview:
        """An overview sharing the built bands and the maps of edits since (persistent: edits
        to one do not touch the other). Cost: O(1)."""
        clone = object.__new__(Overview)
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

    def with_edits(self, edits: dict[str, Any]) -> Overview:
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

    def _edits_in(self, band: int) -> bool:
        """Whether edits changed or added aggregates of ``band`` (or may have: recent ones)."""
        return bool(self._state) or any(band in run.rows for run in self._folded)

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

    # -- internals ---------------------------------------------------------------------------

    def _home(self, item: int) -> tuple[int, int] | None:
        if item in self._member:
            return self._member[item]
        for run in reversed(self._folded):  # the newest run that holds it
            at = _found_one(run.items, item)
            if at is not None:
                level = int(run.level[at])
                return None if level == _DRAWN else (level, int(run.home[at]))
        if not 0 <= item < len(self._homes):
            raise KeyError(f"item {item} is not in the overview")
        if self._watch is not None:  # its block alone: an edit reads a few homes of millions
            self._watch.check(self._homes[item : item + 1])
        (first,), (agg,) = self._split(self._homes[item : item + 1])
        return None if first > self.hi else (int(first), int(agg))

    def _split(self, homes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Built homes as ``(first band, aggregate there)``; ``(hi + 1, -1)`` for -1."""
        at = np.searchsorted(self._starts, homes, side="right") - 1  # a band's that holds none is skipped
        home = homes >= 0
        return np.where(home, self.lo + at, self.hi + 1), np.where(home, homes - self._starts[at], -1)

    def _row(self, band: int, index: int) -> tuple:
        state = self._state.get((band, index))
        if state is not None:
            return state
        for folded in (run.rows[band] for run in reversed(self._folded) if band in run.rows):  # newest first
            at = _found_one(folded.indices, index)
            if at is not None:
                return folded.row(at)
        bands = self._bands
        built = bands.row(band, index) if isinstance(bands, _CheckedBands) else bands.get(band)
        if built is None or not 0 <= index < len(built.count):
            raise KeyError(f"no aggregate {index} in band {band}")
        return _row_at(index, built.boxes, built.count, built.area, built.z, built.kind, built.parent)

    def _tree(self, band: int) -> QuadTree | None:
        tree = self._trees.get(band)
        if tree is not None:
            return tree
        built = dict.get(self._bands, band)  # its tree checks what it reads itself
        return None if built is None else built.tree

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


FOLD_AFTER = 2048  # entries of the maps of recent edits before they are folded into arrays
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


class _CheckedBands(dict[int, _Band]):
    """The bands of an overview mapped from a file: each band's arrays are checked by the
    watch on the band's first use (its tree reports its own reads)."""

    def __init__(self, watch: ReadWatch) -> None:
        super().__init__()
        self._watch, self._seen = watch, set[int]()
        self._rows = set[tuple[int, int]]()  # rows checked alone (bands seen aside)

    def __getitem__(self, level: int) -> _Band:
        band = super().__getitem__(level)
        if level not in self._seen:
            self._watch.check(*band.arrays())
            self._seen.add(level)
        return band

    def get(self, level: int, default: Any = None) -> Any:
        return self[level] if level in self else default  # noqa: SIM401 (checked, as [] is)

    def row(self, level: int, index: int) -> _Band | None:
        """Band ``level``, with aggregate ``index``'s entries checked, not the whole band: an
        edit reads a few rows of each band it changes, which at 1e8 items hold millions."""
        band = dict.get(self, level)
        if band is not None and level not in self._seen and 0 <= index < len(band.count):
            if (level, index) in self._rows:  # once: an edit reads the same rows up the bands
                return band
            at = slice(index, index + 1)
            slot = band.boxes.slot
            self._watch.check(
                slot[at], band.count[at], band.area[at], band.z[at], band.kind[at], band.parent[at]
            )
            self._watch.check(band.boxes.boxes[int(slot[index]) : int(slot[index]) + 1])
            self._rows.add((level, index))  # checked: never again
        return band


def _band_arrays(level: int, band: _Band) -> dict[str, np.ndarray]:
    """Band ``level``'s arrays, named as ``to_arrays`` names them."""
    out = {f"{level}.{name}": getattr(band, name) for name in ("count", "area", "z", "kind", "parent")}
    out[f"{level}.slot"] = band.boxes.slot  # where each aggregate's box is in the tree's
    out.update({f"{level}.tree.{k}": v for k, v in band.tree.to_arrays().items()})
    return out


class _Boxes:
    """A band's elements' boxes: the band below's aggregates' (``below``, gathered), then the
    joining items' (``items[new]``), read where they lie by the kernels that need them (their
    cells, areas and unions), never gathered: 32 bytes an element less through its peak."""

    def __init__(self, below: np.ndarray, items: np.ndarray, new: np.ndarray) -> None:
        self.below, self.items, self.new = below, items, new

    def __len__(self) -> int:
        return len(self.below) + len(self.new)

    def cell_range(self, at: tuple[float, float, float]) -> tuple[int, int, int, int]:
        """The least column and row, and the most, of the elements' cells: ``at`` is the
        origin's halves and a cell's half side (``_kernels.cell_range``)."""
        out = np.array([2**63 - 1, 2**63 - 1, -(2**63), -(2**63)], np.int64)
        for _, rows in in_steps(self.below):
            _kernels.cell_range(rows, None, *at, out)
        for lo, hi in _stepped(self.items, self.new):
            _kernels.cell_range(self.items, self.new[lo:hi], *at, out)
        x0, y0, x1, y1 = out.tolist()
        return x0, y0, x1, y1

    def cell_keys(
        self, at: tuple[float, float, float], x0: int, y0: int, kx: int, ky: int, out: np.ndarray
    ) -> np.ndarray:
        """Each element's cell's key (``_kernels.cell_keys``), into ``out`` (unsigned), its
        pages handed back as they are written (mapped from a file)."""
        held = len(self.below)
        for lo, rows in in_steps(self.below):
            into = out[lo : lo + len(rows)]
            _kernels.cell_keys(rows, None, *at, x0, y0, np.uint64(kx), np.uint64(ky), into)
            release_rows(into)
        _at_rows(
            lambda rows, into: _kernels.cell_keys(
                self.items, rows, *at, x0, y0, np.uint64(kx), np.uint64(ky), into
            ),
            self.items,
            self.new,
            out[held:],
        )
        return out

    def steps(self) -> Iterator[tuple[int, int]]:
        """``(lo, hi)`` ranges of the elements, in order: those of the band below, a step of
        their boxes at a time (``steps``), then the items', a step of the items' boxes at a
        time (``steps_at``)."""
        held = len(self.below)
        yield from steps(held, 32)
        for lo, hi in steps_at(self.new, 32):
            yield held + lo, held + hi

    def release(self, lo: int, hi: int, *columns: np.ndarray) -> None:
        """Hand back the pages of the boxes (mapped from a file: an import's, the band
        below's when spilled), and of ``columns`` (one value an item), that elements
        ``lo..hi`` (a step) read."""
        held = len(self.below)
        release_rows(self.below[lo:hi])
        if hi > held:
            rows = slice(self.new[max(lo - held, 0)], self.new[hi - held - 1] + 1)
            for column in (self.items, *columns):
                release_rows(column[rows])
            release_rows(self.new[max(lo - held, 0) : hi - held])


def _at_rows(
    kernel: Callable[[np.ndarray, np.ndarray], None], items: np.ndarray, rows: np.ndarray, out: np.ndarray
) -> None:
    """``kernel(rows, out)`` (reading ``items`` at ``rows``, ascending) a step of rows at a
    time (``_stepped``), the pages of ``out`` written handed back (mapped from a file)."""
    for lo, hi in _stepped(items, rows):
        kernel(rows[lo:hi], out[lo:hi])
        release_rows(out[lo:hi])


def _stepped(items: np.ndarray, rows: np.ndarray) -> Iterator[tuple[int, int]]:
    """``(lo, hi)`` steps of ``rows`` (ascending, into ``items``): after each, the pages of
    ``items`` it read (or wrote) are handed back (mapped from a file)."""
    for lo, hi in steps_at(rows, items[:1].nbytes or 1):
        yield lo, hi
        release_rows(items[rows[lo] : rows[hi - 1] + 1])
        release_rows(rows[lo:hi])


def _elements(
    previous: _Below | None, boxes: np.ndarray, new: np.ndarray, z: np.ndarray, kinds: np.ndarray
) -> list[Any]:
    """What a band merges: the band below's aggregates, then the items at ``new`` that join
    here. Their boxes, read where they lie (``_Boxes``), and their other columns
    (``_Columns``), each made when it is used, once the elements' cells are sorted and their
    owners found, and let go once reduced."""
    below = np.empty((0, 4)) if previous is None else previous.boxes
    return [_Boxes(below, boxes, new), _Columns(previous, boxes, new, z, kinds)]


class _Columns:
    """The elements' areas, made once their cells are sorted: they sort and sum each
    aggregate's elements, and go (8 bytes an element) before the boxes, counts and z are
    reduced. No other column is made: the band below's counts, z and kinds are its own, an
    item counts 1 at its own z, and of the kinds only each aggregate's largest element's are
    read."""

    def __init__(
        self, previous: _Below | None, boxes: np.ndarray, new: np.ndarray, z: np.ndarray, kinds: np.ndarray
    ) -> None:
        # The band below's aggregates' columns (fewer than the elements), each let go once used
        columns = ("area", "count", "z", "kind")
        self.below = {} if previous is None else {name: getattr(previous, name) for name in columns}
        self.held = 0 if previous is None else len(previous.count)
        self.boxes, self.new, self.z, self.kinds = boxes, new, z, kinds

    def area(self, area: np.ndarray) -> np.ndarray:
        """Each element's area, into ``area`` a step at a time (its pages handed back)."""
        boxes = self.boxes
        for lo, step in in_steps(self.below.pop("area", np.empty(0))):
            into = area[lo : lo + len(step)]
            into[:] = step
            release_rows(into)
        _at_rows(lambda rows, into: _kernels.areas_at(boxes, rows, into), boxes, self.new, area[self.held :])
        return area

    def count_and_z(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The band below's aggregates' counts and z, and the items' z (each item counts 1)."""
        empty = np.empty(0, np.int32)
        return self.below.pop("count", empty), self.below.pop("z", empty), self.z

    def kind_of(self, elements: np.ndarray, out: np.ndarray) -> np.ndarray:
        """The kinds of ``elements`` (a few: each aggregate's largest), into ``out`` (its
        pages handed back once written, mapped from a file)."""
        mine = elements < self.held
        below = self.below.pop("kind", np.empty(0, np.int32))
        out[mine] = below[elements[mine]]
        out[~mine] = self.kinds[self.new[elements[~mine] - self.held]]  # a broadcast column reads one value
        for column in (below, self.kinds, self.new, out):  # mapped: read at random, handed back
            release(column)
        return out


def _merge(
    level: int, ox: float, oy: float, rule: str, elements: list[Any], scratch: Scratch | None = None
) -> tuple[_Band, np.ndarray]:
    """Band ``level`` from its elements (``_elements``' boxes and columns): ``(band, owner)``,
    owner the aggregate of each element. ``elements`` is emptied: each column is let go once
    reduced, before the band's tree is built (the elements outnumber the aggregates)."""
    boxes, columns = elements
    elements.clear()
    half = math.ldexp(1.0, level - 1)  # cell index = (centre - origin) / 2**level, halved first: no overflow
    order, cells, dtype = _cell_order(boxes, ox, oy, half, scratch)
    run, (rx0, rx1, ry) = _cell_runs(cells, 0 if rule == "cells" else 1, dtype, scratch)
    del cells
    if rule == "rectangles":  # runs over the same columns in consecutive rows are one rectangle
        by_columns = _by_columns(rx0, rx1, ry, scratch)
        group = _kernels.rectangle_groups(by_columns, rx0, rx1, ry, TILE)
        release(by_columns)  # (read in order: mapped, its pages handed back)
        del by_columns
    elif rule == "blobs":
        group = _blobs(rx0, rx1, ry)
    else:
        group = np.arange(len(ry))
    del rx0, rx1, ry  # ~12 bytes a run, as many runs as elements in a sparse band
    # Each element's aggregate, a step of the cells at a time: written at random, with
    # ``scratch`` in a file a window of the elements a pass, its pages handed back after each
    owner = new_array(scratch, len(order), order.dtype.type)
    for a, b in windows(len(owner), owner.itemsize, scratch is not None):
        for lo, step in in_steps(order):
            _kernels.owners(step, group, run[lo : lo + len(step)], a, b, owner)
            release_rows(run[lo : lo + len(step)])
        release(owner)
    # Reduce each aggregate's elements: sorted by aggregate, largest area last within each.
    # They are numbered 0.. in order, none empty: each run has a cell
    groups = int(group.max()) + 1 if len(group) else 0
    del order, run, group
    area = columns.area(new_array(scratch, len(owner), np.float64))
    by_owner, starts, area = _group_order(owner, groups, area, scratch)
    # The areas' sums as numpy's pairwise ``reduceat`` makes them (a plain sum would round
    # differently); each kind the largest element's (the last). With ``scratch``, each made
    # in a file, its pages handed back once written: not held through the unions
    areas = _sums(area, starts, new_array(scratch, groups, np.float64))
    del area
    kinds = columns.kind_of(_last_of(by_owner, starts), new_array(scratch, groups, np.int32))
    starts = in_file(starts, scratch)  # for the zeros, at the end
    # Boxes, counts and z in one pass, the elements read where they are
    count, z, item_z = columns.count_and_z()
    del columns
    out, counts, top = _group_union(by_owner, starts, owner, boxes, count, z, item_z, scratch)
    del boxes, count, z, item_z, by_owner, starts
    tree = _band_tree(out, scratch)
    del out
    band = _Band(
        boxes=_TreeBoxes.of(tree, scratch),
        count=counts,
        area=areas,
        z=top,
        kind=kinds,
        parent=filled(new_array(scratch, groups, np.int32), -1),
        tree=tree,
    )
    return band, owner


def _band_tree(boxes: np.ndarray, scratch: Scratch | None) -> QuadTree:
    """The tree over a band's aggregates' ``boxes``, which it takes over (put in its order
    where they lie). With ``scratch`` (``boxes`` in a file), built to be written
    (``QuadTree.build_arrays``): its keys sorted and its boxes and ids made in files a run at
    a time, ``boxes`` read a step at a time: ~45 bytes an aggregate not held (1.2 GB for the
    largest band of a 1e8-item board)."""
    if scratch is None:
        return QuadTree.bulk_load_owned(boxes)
    rows, made = new_array(scratch, boxes.size, np.float64).reshape(-1, 4), 0

    def put(run: np.ndarray) -> None:
        nonlocal made
        into = rows[made : made + len(run)]
        into[:] = run
        release_rows(into)
        made += len(run)

    arrays = QuadTree.build_arrays(boxes, put, scratch=scratch)
    # int64 ids, as a tree built in memory has: the arrays written are the same, to the byte
    return QuadTree.from_arrays({**arrays, "boxes": rows, "ids": in_file(arrays["ids"], scratch, np.int64)})


def _group_steps(starts: np.ndarray, step: int) -> Iterator[tuple[int, int]]:
    """``(g0, g1)``: the groups (``starts`` apart, none empty) that begin in each ``step`` of
    elements, in order (the last of them read to its end)."""
    if len(starts) < 2:
        return
    # (the steps in ``starts``' own type: another would have numpy convert all of them)
    at = np.searchsorted(starts, np.arange(0, starts[-1], step, dtype=starts.dtype), side="right") - 1
    for g0, g1 in zip(at.tolist(), [*at[1:].tolist(), len(starts) - 1], strict=True):
        if g0 < g1:
            yield g0, g1


def _sums(values: np.ndarray, starts: np.ndarray, out: np.ndarray, step: int = 1 << 16) -> np.ndarray:
    """Each group's sum of ``values`` (in the groups' order, ``starts`` apart, none empty), as
    numpy's pairwise ``reduceat`` makes them, into ``out``, a ``step`` of elements at a time:
    no copy of them all; the pages of ``values`` read and of ``out`` written handed back after
    each (mapped from a file)."""
    for g0, g1 in _group_steps(starts, step):
        lo, hi = starts[g0], starts[g1]
        out[g0:g1] = np.add.reduceat(values[lo:hi], starts[g0:g1] - lo)
        release_rows(out[g0:g1])
        release_rows(values[lo:hi])
    return out


def _group_order(
    groups: np.ndarray, count: int, values: np.ndarray, scratch: Scratch | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(order, starts, values[order])``: ``np.lexsort((values, groups))`` (``groups``: ints
    in ``[0, count)``, of a type that holds every position; ``values``: floats, never NaN),
    where each group begins in it (then ``n``), both in the groups' type, and the values in
    that order. A counting sort, ``groups`` and ``values`` read a step at a time (mapped:
    each step's pages handed back), each value put beside its place as it is; then each
    group sorted by its values, a step of groups at a time: no value is read at random. With
    ``scratch``, the order and the values in it are made in files."""
    starts = np.zeros(count + 1, groups.dtype)
    for _, step in in_steps(groups):
        _kernels.group_counts(step, starts)
    np.cumsum(starts, out=starts)
    order, fill = new_array(scratch, len(groups), groups.dtype.type), starts[:-1].copy()
    placed = new_array(scratch, len(groups), values.dtype.type)
    # A pass over the elements for each window of groups: written at random, a window's
    # pages are held at a time (with ``scratch``), not all of both (12 bytes an element)
    window = (
        _paging.WINDOW_BYTES // (order.itemsize + placed.itemsize) if scratch is not None else len(groups)
    )
    for g0, g1 in _group_steps(starts, max(1, window)):
        for lo, step in in_steps(groups):
            _kernels.group_fill(step, lo, fill, order, values[lo : lo + len(step)], placed, g0, g1)
            release_rows(values[lo : lo + len(step)])
        for column in (order, placed):
            release(column)
    del fill
    for g0, g1 in _group_steps(starts, max(1, _paging.STEP_BYTES // 12)):
        _kernels.group_sort(order, starts, placed, g0, g1)
        for column in (order, placed):
            release_rows(column[starts[g0] : starts[g1]])
    return order, starts, placed


def _last_of(order: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Each group's last element in ``order`` (groups ``starts`` apart, none empty), read a
    step at a time (mapped: each step's pages handed back)."""
    last = np.empty(len(starts) - 1, order.dtype)
    for g0, g1 in _group_steps(starts, max(1, _paging.STEP_BYTES // order.itemsize)):
        last[g0:g1] = order[starts[g0 + 1 : g1 + 1] - 1]
        release_rows(order[starts[g0] : starts[g1]])
    return last


def _group_union(
    order: np.ndarray,
    starts: np.ndarray,
    groups: np.ndarray,
    boxes: _Boxes,
    counts: np.ndarray,
    z: np.ndarray,
    item_z: np.ndarray,
    scratch: Scratch | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each group's union of its elements' ``boxes``, summed counts and largest z (the band
    below's ``counts`` and ``z``, then the items', 1 and ``item_z`` at each: see
    ``_kernels.group_union``), the elements read a step at a time. With ``scratch``, the
    three are made in files, written a window of groups a pass (at random), each window's
    pages handed back after its pass."""
    count = len(starts) - 1
    out = new_array(scratch, 4 * count, np.float64).reshape(count, 4)
    for _, rows in in_steps(out):
        rows[:, :2] = np.inf
        rows[:, 2:] = -np.inf
    sums = filled(new_array(scratch, count, np.int32), 0)  # at most n, under 2**31
    top = filled(new_array(scratch, count, np.int32), np.iinfo(np.int32).min)
    # The items' z in one type whatever the caller's column (one compiled variant, which
    # start-up compiles): a column of one value as that value, read with a step of 0
    z_step = 0 if len(item_z) and item_z.strides == (0,) else 1
    item_z = np.array(item_z[:1] if z_step == 0 else item_z, np.int32, copy=None, order="C")
    if not item_z.flags.writeable:
        item_z = item_z.copy()
    # A pass over the elements for each window of groups: written at random, a window's
    # pages are held at a time, not all of the three (40 bytes an aggregate)
    for g0, g1 in windows(count, 40, scratch is not None):
        for lo, hi in boxes.steps():
            _kernels.group_union(
                order,
                starts,
                groups,
                boxes.below,
                boxes.items,
                boxes.new,
                counts,
                z,
                item_z,
                z_step,
                lo,
                hi,
                g0,
                g1,
                out,
                sums,
                top,
            )
            boxes.release(lo, hi, item_z)
            for column in (counts, z, groups):  # the band below's, and each element's group
                release_rows(column[lo:hi])
        for column in (out, sums, top):
            release(column)
    for g0, g1 in steps(count, out.itemsize * 4):
        _kernels.union_zeros(order, starts, boxes.below, boxes.items, boxes.new, g0, g1, out)
        for column in (out, order, starts):  # mapped: handed back
            release(column)
    return out, sums, top


# Sorted cells as ``_kernels.cell_runs`` reads them: columns, rows, keys, width, x0, y0
_Cells = tuple[np.ndarray, np.ndarray, np.ndarray, np.uint64, int, int]


def _by_columns(rx0: np.ndarray, rx1: np.ndarray, ry: np.ndarray, scratch: Scratch | None) -> np.ndarray:
    """``np.lexsort((ry, rx1, rx0))``: the runs by first column, last column, then row. A
    radix sort of one key a run where the three fit 64 bits (with ``scratch``, made and sorted
    in files a run at a time: ``sorted_keys``), numpy's lexsort where they do not (~20 bytes a
    run held, its order and its copies of the columns)."""
    if not len(ry):
        return np.empty(0, np.int64)
    x0, y0 = int(rx0.min()), int(ry.min())
    width, height = int(rx1.max()) - x0 + 1, int(ry.max()) - y0 + 1
    if width * width * height > 1 << 64:
        return np.lexsort((ry, rx1, rx0))
    key = new_array(scratch, len(ry), np.uint64)
    for lo, hi in steps(len(ry), key.itemsize):
        column, last, row = (c[lo:hi].astype(np.int64) for c in (rx0, rx1, ry))
        into = key[lo:hi]
        into[:] = (
            (column - x0).astype(np.uint64) * np.uint64(width) + (last - x0).astype(np.uint64)
        ) * np.uint64(height) + (row - y0).astype(np.uint64)
        release_rows(into)
    return sorted_keys(key, (width * width * height - 1).bit_length(), scratch)[0]


def _cell_runs(
    cells: _Cells, gap: int, dtype: type, scratch: Scratch | None
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``(run, (rx0, rx1, ry))``: each sorted cell's run (elements of one row whose cells
    follow one another with no more than ``gap`` empty cells between, within a tile; "cells":
    a run a cell), and each run's first and last column and row. Read from the sorted keys
    with no column of cells made (8 bytes an element), in two passes a step of them at a
    time; with ``scratch``, ``run`` in a file, each step's pages (and the keys') handed back."""
    keys, n = cells[2], max(len(cells[0]), len(cells[2]))
    run = new_array(scratch, n, _kernels.index_type(n))
    last, runs = np.array([-1, 0, 0], np.int64), 0
    for lo, step in in_steps(run):
        runs = _kernels.cell_runs(*cells, gap, TILE, step, lo, last)
        release_rows(keys[lo : lo + len(step)])
    rx0, rx1, ry = (np.empty(runs, np.dtype(dtype)) for _ in range(3))
    before = -1
    for lo, step in in_steps(run):
        _kernels.run_cells(*cells, step, lo, before, rx0, rx1, ry)
        before = int(step[-1])
        release_rows(keys[lo : lo + len(step)])
    return run, (rx0, rx1, ry)


def _cell_order(
    boxes: _Boxes, ox: float, oy: float, half: float, scratch: Scratch | None = None
) -> tuple[np.ndarray, _Cells, type]:
    """``(order, cells, dtype)``: ``np.lexsort((cx, cy))`` of the boxes' cells
    (``_kernels.cell_keys``), the order that sorts them by row then column; the sorted cells
    as the kernels read them (``_kernels.cell_runs``: a sorted key a cell, or the columns and
    rows); and the type a cell's column or row fits. A radix sort of one key per cell (4
    bytes when a row's and a column's spans fit 32 bits), made from the boxes, sorted in
    place; with ``scratch``, made and sorted in files a run at a time (``sorted_keys``). Two
    stable sorts in memory, one a coordinate, when the spans do not fit 64 bits."""
    at, n = (ox * 0.5, oy * 0.5, half), len(boxes)
    none = np.empty(0, np.int64)
    if not n:
        return (
            np.arange(0, dtype=np.int32),
            (none, none, np.empty(0, np.uint64), np.uint64(0), 0, 0),
            np.int64,
        )
    x0, y0, x1, y1 = boxes.cell_range(at)
    width, height = x1 - x0 + 1, y1 - y0 + 1
    if width * height > 1 << 64:  # no key holds both: by column, then by row (the sort is stable)

        def keys(kx: int, ky: int) -> np.ndarray:
            return boxes.cell_keys(at, x0, y0, kx, ky, np.empty(n, np.uint64))

        order = np.arange(n, dtype=_kernels.index_type(n))  # int32: 4 bytes less through the peak
        order = _kernels.radix_order(keys(1, 0), order, 64)[0]
        order, sy = _kernels.radix_order(keys(0, 1)[order], order, 64)
        sx = keys(1, 0)[order].view(np.int64)
        sx += x0
        sy = sy.view(np.int64)
        sy += y0
        return order, (sx, sy, np.empty(0, np.uint64), np.uint64(0), 0, 0), np.int64
    bits = (width * height - 1).bit_length()
    key = new_array(scratch, n, np.uint32 if bits <= 32 else np.uint64)
    order, key = sorted_keys(boxes.cell_keys(at, x0, y0, 1, width, key), bits, scratch)
    dtype = np.int32 if max(-x0, x1, -y0, y1) < 1 << 31 else np.int64
    return order, (none, none, key, np.uint64(width), x0, y0), dtype


def _blobs(rx0: np.ndarray, rx1: np.ndarray, ry: np.ndarray) -> np.ndarray:
    """Groups of runs (sorted by row, then column) that overlap in consecutive rows, joined."""
    parent = list(range(len(ry)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    rows = np.flatnonzero(np.concatenate(([True], ry[1:] != ry[:-1])))
    bounds = np.append(rows, len(ry)).tolist()
    for a, b, c in zip(bounds[:-2], bounds[1:-1], bounds[2:], strict=True):
        if ry[b] != ry[a] + 1 or ry[b] // TILE != ry[a] // TILE:
            continue
        for i in range(a, b):  # the runs of the next row that overlap run i's columns
            lo = b + int(np.searchsorted(rx1[b:c], rx0[i]))
            for j in range(lo, c):
                if rx0[j] > rx1[i]:
                    break
                parent[root(j)] = root(i)
    roots = np.array([root(i) for i in range(len(ry))], np.int64)
    return np.unique(roots, return_inverse=True)[1]


def _levels(extent: tuple[float, float, float, float], least: float) -> tuple[int, int]:
    """``(lo, hi)``: the top band's cell holds the whole ``extent`` of the items' boxes; the
    lowest is under the smallest positive item (``least``, inf: none; only zero-sized ones
    are merged there), at most ``_SPAN`` below."""
    x0, y0, x1, y1 = extent
    half = max(x1 * 0.5 - x0 * 0.5, y1 * 0.5 - y0 * 0.5)
    hi = min(math.frexp(half)[1] + 1 if half > 0 else 0, 1023)  # 2**hi > the extent, and finite
    lo = math.frexp(least)[1] - 1 if math.isfinite(least) else hi
    return max(lo, hi - _SPAN), hi


def _least_size(boxes: np.ndarray) -> float:
    """The smallest positive finite size (``_sizes``) of ``boxes``, inf if none: a step of
    them at a time."""
    least = math.inf
    for _, rows in in_steps(boxes):
        sizes = _sizes(rows)
        finite = sizes[(sizes > 0) & np.isfinite(sizes)]
        least = min(least, float(finite.min())) if len(finite) else least
    return least


def _first_bands(boxes: np.ndarray, lo: int, hi: int, scratch: Scratch | None) -> np.ndarray:
    """Each item's first band, its size's (``hi + 1``: drawn itself in every band), int16
    (within -1074..1024): made a step of ``boxes`` at a time, in a file with ``scratch`` (its
    pages handed back after each), never a column of sizes held (8 bytes an item)."""
    first = new_array(scratch, len(boxes), np.int16)
    for at, rows in in_steps(boxes):
        sizes = _sizes(rows)
        made = np.where(sizes > 0, np.frexp(sizes)[1], lo)
        np.clip(made, lo, hi + 1, out=made)
        made[~np.isfinite(sizes)] = hi + 1
        into = first[at : at + len(rows)]
        into[:] = made
        release_rows(into)
    return first


def _joining(first: np.ndarray, level: int, count: int, scratch: Scratch | None) -> np.ndarray:
    """The ``count`` items whose first band is ``level``, ascending (int32 while they fit),
    found a step of ``first`` at a time; with ``scratch``, in a file, each step's pages
    handed back (read through the band's merge a step at a time: not held)."""
    if not count:
        return np.empty(0, _kernels.index_type(len(first)))
    out = new_array(scratch, count, _kernels.index_type(len(first)))
    at = 0
    for lo, step in in_steps(first):
        found = np.flatnonzero(step == level)
        into = out[at : at + len(found)]
        into[:] = found + lo
        release_rows(into)
        at += len(found)
    return out


def _sizes(boxes: np.ndarray) -> np.ndarray:
    """``max(w, h)`` as the index computes it: inf where a side overflows (always drawn
    itself); the boxes read a step at a time."""
    sizes = np.empty(len(boxes))
    for lo, rows in in_steps(boxes):
        with np.errstate(over="ignore"):
            np.maximum(rows[:, 2] - rows[:, 0], rows[:, 3] - rows[:, 1], out=sizes[lo : lo + len(rows)])
    return sizes


def _size(box: tuple[float, ...]) -> float:
    return max(box[2] - box[0], box[3] - box[1])


def _area(box: tuple[float, ...]) -> float:
    area = (box[2] - box[0]) * (box[3] - box[1])  # Python floats overflow to inf, silently
    return area if math.isfinite(area) else 0.0


def _contains(outer: tuple[float, ...], inner: tuple[float, ...]) -> bool:
    return outer[0] <= inner[0] and outer[1] <= inner[1] and inner[2] <= outer[2] and inner[3] <= outer[3]


def _everything() -> tuple[float, float, float, float]:
    big = np.finfo(np.float64).max
    return (-big, -big, big, big)
