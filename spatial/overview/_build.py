"""The builds: each band's aggregates merged from the band below's and the items that join
it, bottom-up, under one of the four grouping rules (``RULES``), a step of the elements at a
time.

``_merged`` walks the bands; ``_merge`` makes one: its elements filed by the cell their centre
is in (``_cell_order``), cut into runs of a row (``_cell_runs``), the runs grouped by the rule,
then each group's areas, kind, boxes, counts and z reduced (``_group_order``, ``_sums``,
``_group_union``) and the band's tree built over its boxes (``_band_tree``). Apart from the
reads and the edits because it is the one part whose cost is the whole document: each array
here can be made in a file (``scratch``) and is read a step at a time, so a build holds a few
columns and a band's elements, never every band (``tests/test_build_memory.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import _kernels, paging
from ..budget import current
from ..paging import (
    Scratch,
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
from ..quadtree import QuadTree
from ..sorting import sorted_keys

if TYPE_CHECKING:
    from ._reads import _Reads

__all__ = ["RULES", "TILE"]

RULES = ("rectangles", "rows", "cells", "blobs")  # how occupied cells make aggregates: see build()
_SPAN = 52  # bands below the top one at most: cells finer than float spacing tell nothing apart
# An aggregate spans at most TILE x TILE cells of its band: tiles aligned on the band's grid cut
# the groups, so an aggregate's shape (its mask, drawn pixel for pixel) stays a bounded size.
TILE = 8


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


def _merged(
    view: _Reads,
    boxes: np.ndarray,
    kinds: np.ndarray,
    z: np.ndarray,
    rule: str,
    first: np.ndarray,
    origin: tuple[float, float],
    scratch: Scratch | None,
) -> Iterator[tuple[int, _Band]]:
    """The bands of ``view`` merged from the items, ``first`` each one's first band (its homes
    and their starts made on the way); see ``Overview._building``. The build holds a few
    columns at a time: its peak ~14 bytes an item above its input on a board, built as an
    import builds it, with ``scratch`` (``tests/test_build_memory.py``)."""
    lo, hi = view.lo, view.hi
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
        for a, b in _stepped(view._homes, new):
            view._homes[new[a:b]] = owner[joined + a : joined + b]
        release(owner)  # read in order: mapped, its pages handed back
        del owner
        held.append(len(band.count))
        # What the band above merges of it, its boxes gathered in its aggregates' order
        # before it is handed over: its tree (the boxes in its order) can then go once
        # written, never held beside the gathered copy and the next band's columns
        previous = _below(band, scratch)
        yield level, band
        del band
    view._starts = np.concatenate((np.zeros(1, np.int64), np.cumsum(held, dtype=np.int64)))
    starts = view._starts.astype(np.int32)  # numbered across the bands: under 2**31
    for at, step in in_steps(view._homes):  # a step's pages handed back after it
        firsts = first[at : at + len(step)]
        home = firsts <= hi
        step[home] += starts[firsts[home] - lo]
        release_rows(firsts)


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
        current().window_bytes // (order.itemsize + placed.itemsize) if scratch is not None else len(groups)
    )
    for g0, g1 in _group_steps(starts, max(1, window)):
        for lo, step in in_steps(groups):
            _kernels.group_fill(step, lo, fill, order, values[lo : lo + len(step)], placed, g0, g1)
            release_rows(values[lo : lo + len(step)])
        for column in (order, placed):
            release(column)
    del fill
    for g0, g1 in _group_steps(starts, max(1, paging.STEP_BYTES // 12)):
        _kernels.group_sort(order, starts, placed, g0, g1)
        for column in (order, placed):
            release_rows(column[starts[g0] : starts[g1]])
    return order, starts, placed


def _last_of(order: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Each group's last element in ``order`` (groups ``starts`` apart, none empty), read a
    step at a time (mapped: each step's pages handed back)."""
    last = np.empty(len(starts) - 1, order.dtype)
    for g0, g1 in _group_steps(starts, max(1, paging.STEP_BYTES // order.itemsize)):
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
