"""An overview's state and every read of it: the band for a zoom (``band``, ``choose``), the
aggregates in a viewport (``query``, ``diff``), their rows and boxes, the aggregate each item
belongs to at a band (``aggregate_of``, ``homes``), and the pixels their members cover
(``masks``).

A read sees the built bands through the edits since: the recent ones in maps, then the runs
they were folded into (``_folded``), newest first. ``_Reads`` holds what an overview is made
of; ``_Edits`` (``_edits``) adds the edits to it, and ``Overview`` (the package) how it is
built, saved and opened. ``_CheckedBands``: the bands of an overview mapped from a file, each
checked on its first read.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from immutables import Map

from ..quadtree import QuadTree, ReadWatch
from ..raster import occupancy
from ..rect import RectLike
from ..sorting import found_in
from ._build import _Band, _sizes
from ._folded import _DRAWN, _Folded, _found_one, _held, _row_at

__all__ = ["Aggregate", "band_for_size"]

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


class _Reads:
    """What an overview is made of, and every read of it (``Overview``: these with its edits,
    and how it is built, saved and opened)."""

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

    def _edits_in(self, band: int) -> bool:
        """Whether edits changed or added aggregates of ``band`` (or may have: recent ones)."""
        return bool(self._state) or any(band in run.rows for run in self._folded)

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
