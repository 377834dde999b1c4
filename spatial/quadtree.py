"""QuadTree: a bulk-loaded, query-optimised quadtree over boxes, with cheap edits and diffs.

How it is laid out (see ``_kernels`` for the arrays):

- Items are ordered by the quadtree cell of their centre (Morton order in a square world), so
  every node owns one contiguous range of items and a node lying inside a viewport is
  answered by copying its range. A node splits at the first quadrant where its items differ:
  the tree subdivides only where items are, and never deeper than the float spacing allows.
- Each node keeps the exact union of its items' boxes, not its cell: an item that straddles a
  split line widens its own leaf instead of piling up at the root, and pruning compares
  stored floats only, so no rounding can lose an item.
- Leaves are sorted by x0 (the x-order), so a leaf scan stops at the viewport's right edge.
- Edits never touch the built arrays: removals are tombstones, inserts go to a small
  unsorted buffer scanned with every query, and the tree rebuilds itself once either grows.
- A copy shares its tombstones: each records when it was made, and a tree sees those made up
  to its own clock. Copying a tree before each edit (the service's snapshots) costs nothing
  per item, however large the tree.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol, Self, TypedDict, Unpack

import numpy as np
from immutables import Map

from . import _kernels, _layout, _walk
from ._lookup import Lookup
from .budget import MemoryBudget, current
from .paging import Scratch, mapping, release_rows
from .rect import RectLike, as_box_array, as_id, as_ids, as_min_size, as_rect, touches
from .sorting import sorted_keys

__all__ = ["QuadTree", "ReadWatch"]

MinSize = float | tuple[float, float]


class ReadWatch(Protocol):
    """Where a tree over arrays mapped from a file (``from_arrays``) reports what it reads, so
    that each block of the file is checked before an answer that read it is returned."""

    marks: np.ndarray  # uint8 a block: 0 unread, 1 checked, 2 read and not checked, 3 bad
    # int64: [0] bumped by a walk for each block it marks, [1 + b >> READ_RUN] set for block b's run
    pending: np.ndarray

    def places(self, arrays: Sequence[np.ndarray]) -> np.ndarray:
        """int64 ``shift``, then ``offset, row bytes`` of each array in the file."""
        ...

    def settle(self) -> None:
        """Check the blocks marked read. :raises: if one is bad"""
        ...

    def check(self, *arrays: np.ndarray) -> None:
        """Check every block of ``arrays``. :raises: if one is bad"""
        ...

    def prefetch(self, blocks: np.ndarray) -> None:
        """Have ``blocks`` read from the file now, ahead of the reads that need them."""
        ...


class Options(TypedDict, total=False):
    """The constructor's options, as ``bulk_load`` passes them on."""

    leaf_size: int
    max_depth: int
    x_order: bool
    coords: str


class QuadTree:
    """A set of ``(id, box)`` items answering viewport queries and viewport diffs.

    >>> tree = QuadTree.bulk_load([[0, 0, 10, 10], [20, 0, 30, 10]])
    >>> tree.query((10, 0, 15, 5)).tolist()
    [0]
    >>> entered, left = tree.diff((0, 0, 15, 5), (16, 0, 25, 5))
    >>> entered.tolist(), left.tolist()
    ([1], [0])
    """

    _watch: ReadWatch | None = None  # reads of arrays mapped from a file are reported to it
    _places: np.ndarray  # with a watch: where the nodes, boxes and ids lie in its file
    #: The compiled query and diff of this build's arrays, without edits (True) and with them
    _walks: dict[bool, tuple[Callable[..., np.ndarray], Callable[..., tuple[np.ndarray, int]]]]
    _lookup: Lookup | None  # where each built id sits: made on the first edit, or given
    #: Inserts buffered (or 4x as many rows, removed ones too; and tombstones, past a quarter
    #: of the items) before the tree rebuilds itself: 256 + n/512 after each build, so the
    #: linear scan of the buffer stays a small part of a query. Set it higher when something
    #: else rebuilds the tree sooner (the service compacts a document in the background): an
    #: edit then never waits for one.
    max_buffered: int

    def __init__(
        self,
        *,
        leaf_size: int = 32,
        max_depth: int = _kernels.MAX_DEPTH,
        x_order: bool = True,
        coords: str = "float64",
    ) -> None:
        """An empty tree.

        ``leaf_size``: items a leaf holds before it splits. ``max_depth``: the most times a
        cell is halved (fewer when the coordinates' float spacing is reached first).
        ``x_order``: sort each leaf by x0 so scans stop at the viewport's right edge.
        ``coords="float32"`` stores built boxes in half the memory, each rounded outward to
        the next float32, so a query never misses an item but may return one that only its
        rounded box touches (a false hit: a candidate, as with ``exact=False``). ``get``
        then answers the rounded box. Coordinates beyond float32's range (3.4e38) are refused.
        """
        if coords not in ("float64", "float32"):
            raise ValueError(f"coords must be 'float64' or 'float32', got {coords!r}")
        self.coords = coords
        if not 1 <= int(leaf_size) <= 1 << 20:
            raise ValueError(f"leaf_size must be between 1 and 2**20, got {leaf_size!r}")
        if not 0 <= int(max_depth) <= _kernels.MAX_DEPTH:
            raise ValueError(f"max_depth must be between 0 and {_kernels.MAX_DEPTH}, got {max_depth!r}")
        self.leaf_size = int(leaf_size)
        self.max_depth = int(max_depth)
        self.x_order = bool(x_order)
        self._load(np.empty((0, 4), np.float64), np.empty(0, np.int64))

    @classmethod
    def bulk_load(cls, boxes: object, ids: object = None, **options: Unpack[Options]) -> Self:
        """A tree holding ``boxes`` (n, 4) float64 under ``ids`` (int64, default ``0..n-1``).

        Cost: O(n): a radix sort by cell, then one pass (~0.2 s for 1M boxes). ``options``
        are those of the constructor.

        :raises ValueError: if a box is not finite or inverted (naming the first bad row), or if
            ids are not n unique integers in int64's range (naming the first bad one, or a repeated one)
        """
        tree = cls(**options)
        boxes = as_box_array(boxes)
        tree._load(boxes, None if ids is None else as_ids(ids, boxes.shape[0]), check_ids=ids is not None)
        return tree

    @classmethod
    def bulk_load_owned(cls, boxes: np.ndarray, **options: Unpack[Options]) -> Self:
        """``bulk_load(boxes)`` of boxes it takes over: a float64 ``boxes`` is put in the
        tree's order in place and kept as the tree's own, where ``bulk_load`` copies it (32
        bytes an item less at the build's peak). The caller must not use ``boxes`` after.

        :raises ValueError: as ``bulk_load``
        """
        tree = cls(**options)
        tree._load(as_box_array(boxes), None, in_place=True)
        return tree

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The built tree as named arrays (``from_arrays`` takes them back), to save it.

        :raises ValueError: if the tree has edits since its build (``compact()`` it first)
        """
        if self._n_dead or len(self._extra_index):
            raise ValueError("a tree with edits since its build cannot be saved; compact() it first")
        return {"nodes": self._nodes, "boxes": self._boxes, "ids": self._built_ids(), "shape": self._shape()}

    @classmethod
    def build_arrays(
        cls,
        boxes: object,
        put: Callable[[np.ndarray], object],
        scratch: Scratch | None = None,
        *,
        budget: MemoryBudget | None = None,
        **options: Unpack[Options],
    ) -> dict[str, np.ndarray]:
        """``bulk_load(boxes).to_arrays()`` with no tree made, to be written: its boxes, in the
        tree's order, handed to ``put`` a run of whole leaves at a time (about the
        ``run_bytes`` of ``budget``; None: the budget held, ``budget.current()``),
        in order, each let go after; the other arrays returned, ``ids`` (each slot's position
        in ``boxes``) int32 while they fit. Each run is gathered by a pass over ``boxes``,
        read where they lie a step at a time: the build holds a run of the boxes, never all
        of them (32 bytes an item less than ``bulk_load``), and 4 bytes an item for ``ids``
        where a tree's take 8. With ``scratch``, ``ids`` and each box's slot are kept in
        files once the keys are sorted, read a run (or a step) at a time and handed back: 8
        bytes an item not held beside the nodes and a run of the boxes. The sort and the
        windows of files inside it hold ``budget`` too.

        :raises ValueError: as ``bulk_load``, or if ``options`` ask for float32 boxes
        """
        tree = cls(**options)
        if tree.coords != "float64":
            raise ValueError("build_arrays builds float64 trees; bulk_load builds float32 ones")
        boxes = as_box_array(boxes)
        with (budget or current()).held() as held:
            order, link = tree._ranges(boxes, scratch)
            nodes = _layout.aligned_empty((len(link), 8), np.float64)
            leaves = np.flatnonzero(link[:, 2] == link[:, 3])
            leaves = leaves[np.argsort(link[leaves, 0], kind="stable")]  # by their items: they tile 0..n
            place = _layout.slots(order, scratch)
            run = max(1, held.run_bytes // 32)
            for k0, k1, a, b in _layout.leaf_runs(link[leaves, 0].astype(np.int64), len(boxes), run):
                rows = _layout.placed_rows(boxes, place, a, b, np.empty((b - a, 4)))
                _kernels.fill_leaves(link, leaves[k0:k1], rows, a, order, tree.x_order, nodes)
                release_rows(order[a:b])
                put(rows)
                del rows
            _kernels.fill_parents(link, nodes)
        return {"nodes": nodes, "ids": order, "shape": tree._shape()}

    def _shape(self) -> np.ndarray:
        return np.array([self.leaf_size, self.max_depth, self.x_order, self.coords == "float32"], np.int64)

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], watch: ReadWatch | None = None) -> Self:
        """A tree over ``to_arrays``' arrays, used as they are (read-only, mapped from a file,
        say: the built arrays are never written). Cost: O(1) in the items. With
        ``watch``, every read of them is reported to it before a query or diff returns. A
        fifth number in ``shape``, 1, says the ids are ``0..n-1`` in order: finding an id's
        place is then the id, with nothing to build or read, and ``ids`` may be left out.

        :raises ValueError: if the arrays do not make a tree
        """
        try:
            leaf_size, max_depth, x_order, float32, *slots = (int(v) for v in arrays["shape"])
            nodes, boxes = arrays["nodes"], arrays["boxes"]
            ids = _SLOT_IDS if slots and slots[0] and "ids" not in arrays else arrays["ids"]
        except (KeyError, ValueError) as error:
            raise ValueError(f"not a tree's arrays: {error}") from None
        n = len(boxes)
        if (
            nodes.ndim != 2
            or nodes.shape[1:] != (8,)
            or boxes.ndim != 2
            or boxes.shape[1:] != (4,)
            or len(ids) not in (n, 0)
            or (n == 0) != (len(nodes) == 0)
        ):
            raise ValueError(
                f"not a tree's arrays: nodes {nodes.shape}, boxes {boxes.shape}, ids {ids.shape}"
            )
        tree = cls(
            leaf_size=leaf_size,
            max_depth=max_depth,
            x_order=bool(x_order),
            coords="float32" if float32 else "float64",
        )
        tree._boxes, tree._ids, tree._nodes = boxes, ids, nodes
        tree._mapped = True
        if watch is not None:
            tree._watch, tree._places = watch, watch.places([nodes, boxes, ids])
        tree._n, tree._n_dead = n, 0
        tree._dead, tree._clock = None, 0
        tree.max_buffered = 256 + n // 512
        if slots and slots[0]:  # its ids are 0..n-1 in order (a snapshot file's): nothing to build
            tree._lookup = Lookup.identity(n)
        tree._walks = {}  # read-only arrays are other types: compiled code of their own
        tree._pack()
        return tree

    # -- queries -----------------------------------------------------------------------------

    def query(self, rect: RectLike, *, exact: bool = True, min_size: float = 0.0) -> np.ndarray:
        """Ids of items whose box intersects or touches ``rect``, in no particular order.

        Cost: O(log n + k) for k results. With ``exact=False`` the leaves touching ``rect``
        come back untested: a superset, faster. With ``min_size`` (level of detail), items
        whose ``max(w, h) < min_size`` are left out.

        :raises ValueError: if ``rect`` is not finite or has x0 > x1 or y0 > y1, or if
            ``min_size`` is not one finite number >= 0
        """
        x0, y0, x1, y1 = as_rect(rect)
        size = as_min_size(min_size)
        flags = self._flags if exact else self._flags | _walk.INEXACT
        found = self._query(self._arrays, flags, x0, y0, x1, y1, size)
        if self._watch is not None and self._watch.pending[0]:
            self._watch.settle()
        return found

    def diff(
        self, old_rect: RectLike, new_rect: RectLike, *, min_size: MinSize = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(entered, left)``: exactly ``query(new) - query(old)`` and ``query(old) - query(new)``.

        ``min_size`` is one value for both viewports or an ``(old, new)`` pair (tuple or list),
        as when zooming.
        Cost: proportional to the nodes touching the strips where the two viewports differ, not
        to what they hold: a small pan step costs about one query's walk and returns only the
        changed ids. When the sizes differ, every node of either viewport may change.

        :raises ValueError: if a rect is invalid, or if ``min_size`` is not one finite number
            >= 0 or a pair of them
        """
        old, new = as_rect(old_rect, "old_rect"), as_rect(new_rect, "new_rect")
        if isinstance(min_size, (tuple, list)):  # a tuple: a union type is built anew each call
            if len(min_size) != 2:
                raise ValueError(f"min_size must be one number or an (old, new) pair, got {min_size!r}")
            old_size, new_size = as_min_size(min_size[0]), as_min_size(min_size[1])
        else:
            old_size = new_size = as_min_size(min_size)
        ids, k = self._diff(self._arrays, self._flags, *new, new_size, *old, old_size)
        if self._watch is not None and self._watch.pending[0]:
            self._watch.settle()
        return ids[:k], ids[k:]

    def cells(self, rect: RectLike, *, limit: int = 4096) -> list[tuple[int, tuple[float, ...], bool]]:
        """``(depth, box, leaf)`` of the nodes whose box touches ``rect``, shallowest first, at
        most ``limit`` of them: the tree's structure, to draw it. A node's box is the union of
        its items' boxes, not its cell. Cost: O(limit) in Python; a debugging aid, not a query.

        :raises ValueError: if ``rect`` is invalid
        """
        rect = as_rect(rect)
        self._read_all()
        nodes, links = self._nodes, self._links()
        out: list[tuple[int, tuple[float, ...], bool]] = []
        level = [0] if nodes.shape[0] else []
        depth = 0
        while level and len(out) < limit:
            deeper: list[int] = []
            for i in level:
                box = nodes[i, :4]
                if touches(box, rect) and len(out) < limit:
                    leaf = links[i, 2] == links[i, 3]
                    out.append((depth, tuple(box.tolist()), bool(leaf)))
                    deeper.extend(range(links[i, 2], links[i, 3]))
            level, depth = deeper, depth + 1
        return out

    def __len__(self) -> int:
        return self._n - self._n_dead + len(self._extra_index)

    def __contains__(self, item_id: object) -> bool:
        """Whether ``item_id`` is in the tree. Cost: O(log n). Anything that is not an id (a
        float, even 8.0; a bool; an int beyond int64) is answered False, as a missing id is.

        >>> tree = QuadTree.bulk_load([[0, 0, 1, 1]])
        >>> 0 in tree, 0.0 in tree
        (True, False)
        """
        try:
            item_id = as_id(item_id)
        except ValueError:
            return False
        return self._locate(item_id) is not None

    def get(self, item_id: int) -> tuple[float, float, float, float]:
        """The box of ``item_id``. Cost: O(log n).

        :raises ValueError: if the id is not an integer in int64's range
        :raises KeyError: if the id is not in the tree
        """
        kind, index = self._require(as_id(item_id))
        if kind == "extra":
            return tuple(self._inserts.boxes[index].tolist())
        if self._watch is not None:  # the one box read, not every array
            self._watch.check(self._boxes[index : index + 1])
        return tuple(self._boxes[index].tolist())

    @property
    def bounds(self) -> tuple[float, float, float, float] | None:
        """Union of the boxes of the items in the tree now; None when empty. Cost: O(1) until
        an item is removed or moved, O(n) after (until the next rebuild).

        >>> tree = QuadTree.bulk_load([[0, 0, 1, 1], [5, 5, 9, 9]])
        >>> tree.remove(1); tree.bounds
        (0.0, 0.0, 1.0, 1.0)
        """
        if len(self) == 0:
            return None
        parts = [self._inserts.boxes[: self._n_extra][self._extra_live()]]
        if self._n_dead:  # the root's box may still hold removed or moved items
            self._read_all()
            parts.append(self._boxes[self._live_mask()])
        elif self._nodes.shape[0]:
            if self._watch is not None:  # the root's record read, not every array (GBs at 1e8)
                self._watch.check(self._nodes[:1])
            parts.append(self._nodes[:1, :4])
        stacked = np.concatenate(parts)
        return (
            float(stacked[:, 0].min()),
            float(stacked[:, 1].min()),
            float(stacked[:, 2].max()),
            float(stacked[:, 3].max()),
        )

    @property
    def nbytes(self) -> int:
        """Bytes of index beyond the boxes and ids themselves (nodes, tombstones, id lookup)."""
        lookup = self._lookup.nbytes if self._lookup is not None else 0
        dead = self._dead.at.nbytes if self._dead is not None else 0
        return self._nodes.nbytes + dead + lookup

    @property
    def depth(self) -> int:
        """Levels from the root to the deepest leaf (0 for an empty tree)."""
        self._read_all()
        link = self._links()
        level = np.zeros(link.shape[0], np.int64)
        for i in range(link.shape[0]):  # breadth-first order: parents before children
            level[link[i, 2] : link[i, 3]] = level[i] + 1
        return int(level.max()) + 1 if level.size else 0

    def copy(self) -> QuadTree:
        """An independent tree sharing the built arrays, the tombstones and the insert buffer
        (rows are only ever added to it, and removed by a tombstone's tick; its index is a
        persistent map). Cost: O(1), whatever the edits buffered. The first of two trees edited
        after one copy pays nothing more; the second (a fork) then copies the tombstones, 2
        bytes an item, and the buffer.

        Readers can keep querying a copy while the original is edited: the service's snapshots.
        """
        clone = object.__new__(QuadTree)
        clone.__dict__.update(self.__dict__)
        return clone

    def locate_by(self, slots: np.ndarray) -> None:
        """Find items by ``slots`` (ids ``0..n-1``: each id's slot, the inverse of the tree's
        ids, kept by the tree's owner) instead of a lookup made from every id at the first
        edit: an edit then reads the entry it needs (checked first, when mapped from a file).

        :raises ValueError: if ``slots`` is not one entry an item
        """
        if len(slots) != self._n:
            raise ValueError(f"{len(slots)} slots for a tree of {self._n} built items")
        self._lookup = Lookup(0, slots, None, watch=self._watch)

    # -- edits -------------------------------------------------------------------------------

    def edits(self) -> dict[str, np.ndarray]:
        """The edits since the tree was made over its arrays (``from_arrays``), as arrays
        (``with_edits`` makes them again over the same arrays): the built slots removed, and
        the ids and boxes of the inserts live, in the order they were buffered. Cost:
        O(edits), plus a pass over the tombstones.

        :raises ValueError: if the tree rebuilt itself since: its arrays are its own
        """
        if not self._mapped:
            raise ValueError(
                "the tree was built, not mapped, or rebuilt itself since: its edits are all of it"
            )
        dead = np.flatnonzero(~self._live_mask()) if self._n_dead else np.empty(0, np.int64)
        rows = np.flatnonzero(self._extra_live())
        return {
            "dead": dead.astype(np.int64),
            "ids": self._inserts.ids[rows],
            "boxes": self._inserts.boxes[rows],
            "max_buffered": np.array([self.max_buffered], np.int64),
        }

    def with_edits(self, edits: dict[str, np.ndarray]) -> QuadTree:
        """A copy of this tree, with no edits, with ``edits`` (``edits()``) made again at once:
        the built items removed, by slot (``dead``) or by id (``removed``), and the inserts
        (``ids``, ``boxes``), with ``max_buffered`` if given. Not rebuilt, however many (an
        open would pay for a rebuild the edits one at a time may have made): the next edit
        rebuilds it if they are past ``max_buffered``. Cost: O(edits), plus the tombstones
        made (2 bytes an item).

        :raises ValueError: if ``edits`` do not fit the tree, or it has edits of its own
        :raises KeyError: if an id removed is not one of its built items
        """
        if self._n_dead or self._n_extra:
            raise ValueError("edits are made again over a tree with none of its own")
        tree = self.copy()
        ids, boxes = edits["ids"], edits["boxes"]
        dead = edits.get("dead")
        if dead is None:
            removed = edits["removed"]
            dead = self._built_lookup().find_many(removed)
            if len(dead) and int(dead.min()) < 0:
                raise KeyError(f"id {int(removed[np.argmin(dead)])} is not in the tree")
        if len(dead):
            if int(dead.max()) >= tree._n or int(dead.min()) < 0:
                raise ValueError(f"a removed slot past the tree's {tree._n} built items")
            at = np.zeros(tree._n, np.uint16)
            at[dead] = _NEVER - 1
            tree._dead, tree._clock, tree._n_dead = _Tombstones(at), 1, len(dead)
            tree._dead.tip = 1
        k = len(ids)
        inserts = tree._inserts = _Inserts(max(2 * k, 16))
        inserts.boxes[:k], inserts.ids[:k], inserts.count = boxes, ids, k
        tree._n_extra = k
        tree._extra_index = Map(zip(ids.tolist(), range(k), strict=True))
        if "max_buffered" in edits:
            tree.max_buffered = int(edits["max_buffered"][0])
        tree._pack()
        return tree

    def insert(self, item_id: int, box: RectLike) -> None:
        """Add ``item_id`` with ``box``; visible to the next query. Cost: amortised O(1), plus a
        rebuild once ``max_buffered`` edits are buffered.

        :raises ValueError: if the id is not an integer in int64's range, the box is invalid,
            or the id is already in the tree
        """
        item_id = as_id(item_id)
        checked = as_rect(box, "box")
        if self._locate(item_id) is not None:
            raise ValueError(f"id {item_id} is already in the tree; use update() to move it")
        self._append_extra(item_id, checked)
        self._maybe_compact()

    def remove(self, item_id: int) -> None:
        """Remove ``item_id``. Cost: O(log n), plus a rebuild when tombstones pile up.

        :raises ValueError: if the id is not an integer in int64's range
        :raises KeyError: if the id is not in the tree
        """
        item_id = as_id(item_id)
        where, index = self._require(item_id)
        if where == "extra":
            self._remove_extra(item_id, index)
        else:
            self._tombstone(index)
        self._pack()
        self._maybe_compact()

    def update(self, item_id: int, box: RectLike) -> None:
        """Move ``item_id`` to ``box``. Cost: O(log n).

        :raises ValueError: if the id is not an integer in int64's range, or the box is invalid
        :raises KeyError: if the id is not in the tree
        """
        item_id = as_id(item_id)
        checked = as_rect(box, "box")
        where, index = self._require(item_id)
        if where == "extra":
            self._remove_extra(item_id, index)
        else:
            self._tombstone(index)
        self._append_extra(item_id, checked)  # packs the arrays again, the new flags with them
        self._maybe_compact()

    def compact(self) -> None:
        """Rebuild from the live items, merging inserts and dropping tombstones. Cost: O(n)."""
        self._read_all()
        live = self._live_mask() if self._n_dead else slice(None)
        extra = self._extra_live()
        boxes = np.concatenate([self._boxes[live], self._inserts.boxes[: self._n_extra][extra]])
        ids = np.concatenate([self._built_ids()[live], self._inserts.ids[: self._n_extra][extra]])
        self._load(boxes, ids, check_ids=False)

    # -- invariants --------------------------------------------------------------------------

    def _check(self) -> None:
        """Assert every structural invariant; the tests call this after each mutation."""
        self._read_all()
        link, node_box = self._links(), self._nodes[:, :4]
        node_size = self._nodes[:, _kernels.SMIN : _kernels.SMAX + 1]
        n, m = self._n, link.shape[0]
        alive = self._live_mask() if self._dead is not None else np.ones(n, np.bool_)
        assert self._boxes.shape == (n, 4) and self._built_ids().shape == (n,) and alive.shape == (n,)
        assert self._n_dead == n - int(alive.sum())
        assert (m == 0) == (n == 0)
        if m:
            assert link[0, 0] == 0 and link[0, 1] == n
        boxes = self._boxes.astype(np.float64)  # float32 boxes are sized in float64, as the kernels do
        sizes = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
        for i in range(m):
            lo, hi, clo, chi = link[i]
            assert lo < hi, f"node {i} is empty"
            items = self._boxes[lo:hi]
            assert (node_box[i, :2] <= items[:, :2]).all() and (items[:, 2:] <= node_box[i, 2:]).all()
            assert node_size[i, 0] <= sizes[lo:hi].min() and sizes[lo:hi].max() <= node_size[i, 1]
            if clo == chi:
                if self.x_order:
                    assert (np.diff(items[:, 0]) >= 0).all(), f"leaf {i} is not sorted by x0"
                continue
            assert i < clo <= chi <= m and chi - clo >= 2, f"node {i} has {chi - clo} children"
            assert link[clo, 0] == lo and link[chi - 1, 1] == hi
            assert (link[clo + 1 : chi, 0] == link[clo : chi - 1, 1]).all(), f"node {i} children gap"
        inserts, extra = self._inserts, self._extra_live()
        assert self._n_extra <= inserts.count <= len(inserts.ids)
        assert int(extra.sum()) == len(self._extra_index)
        for item_id, index in self._extra_index.items():
            assert inserts.ids[index] == item_id and extra[index], f"id {item_id}'s row is not live"
            assert self._locate_built(item_id) is None, f"id {item_id} is live twice"
        ids = np.concatenate([self._built_ids()[alive], inserts.ids[: self._n_extra][extra]])
        assert np.unique(ids).size == ids.size == len(self)

    # -- internals ---------------------------------------------------------------------------

    def _load(
        self, boxes: np.ndarray, ids: np.ndarray | None, *, check_ids: bool = False, in_place: bool = False
    ) -> None:
        """Build over ``boxes`` under ``ids`` (None: ``0..n-1``, their order then their ids, with
        no array of them held through the build: 16 bytes an item less at its peak).
        ``in_place``: ``boxes`` are the caller's no more: put in the tree's order where they lie."""
        n = boxes.shape[0]
        if check_ids and ids is not None and n:
            lookup_order = np.argsort(ids, kind="stable")
            sorted_ids = ids[lookup_order]
            repeated = np.flatnonzero(sorted_ids[1:] == sorted_ids[:-1])
            if repeated.size:
                raise ValueError(f"id {sorted_ids[repeated[0]]} appears more than once; ids must be unique")
        tree_boxes, order, nodes = self._built(boxes, in_place)
        self._boxes, self._ids = tree_boxes, order.astype(np.int64) if ids is None else ids[order]
        self._nodes = nodes
        self._watch = None  # arrays of its own now
        self._mapped = False  # True over arrays made elsewhere (``from_arrays``): what ``edits`` needs
        self._n, self._n_dead = n, 0
        # The tombstones, 2 B an item, made at the first removal: until then nothing is dead,
        # and an open and a query need none
        self._dead: _Tombstones | None = None
        self._clock = 0  # the tombstones this tree sees: those made at or before it
        self._lookup = None  # built on the first edit: most trees never see one
        self._inserts = _Inserts(16)
        self._extra_index: Map[int, int] = Map()  # id -> its live row: persistent, shared by copies
        self._n_extra = 0  # the rows of ``_inserts`` this tree sees, live or removed
        self.max_buffered = 256 + n // 512
        self._walks = {}  # the arrays' types may differ from the last build's (float32)
        self._pack()

    def _built(self, boxes: np.ndarray, in_place: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The build over ``boxes``: ``(boxes, order, nodes)``, the boxes in the tree's order
        (float32 ones rounded outward), where each came from (int32 while they fit) and the
        nodes' records. ``in_place``: as ``_load``'s.

        :raises ValueError: if there are more than ``MAX_ITEMS`` boxes
        """
        if self.coords == "float32":  # built from the rounded boxes, so the nodes contain them
            boxes = _layout.outward_float32(boxes).astype(np.float64)
        order, link = self._ranges(boxes)
        if in_place and self.coords == "float64" and boxes.flags.writeable and boxes.flags.c_contiguous:
            _kernels.gather_in_place(boxes, order)
            tree_boxes = boxes
        elif mapping(boxes) is not None:  # an import's, in a file: read where they lie, not at random
            tree_boxes = _layout.in_order(boxes, order)
        else:  # mode="clip": with the default, numpy buffers a take into ``out`` (a second copy)
            tree_boxes = np.take(
                boxes, order, axis=0, out=_layout.aligned_empty(boxes.shape, np.float64), mode="clip"
            )
        nodes = _layout.aligned_empty((len(link), 8), np.float64)
        leaves = np.flatnonzero(link[:, 2] == link[:, 3])
        _kernels.fill_leaves(link, leaves, tree_boxes, 0, order, self.x_order, nodes)  # the order final then
        _kernels.fill_parents(link, nodes)
        del link
        if self.coords == "float32":  # exact: they are float32 values already
            tree_boxes = _layout.aligned(tree_boxes.astype(np.float32))
        return tree_boxes, order, nodes

    def _ranges(self, boxes: np.ndarray, scratch: Scratch | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(order, link)``: the items by key (int32 while they fit), and the nodes' ranges
        over them (``_kernels.split``), the keys made, sorted and let go between. With
        ``scratch``, the keys and ``order`` are made and sorted in its files a run at a time
        (``sorted_keys``), and split a step of them at a time: 12 bytes an item not held.

        :raises ValueError: if there are more than ``MAX_ITEMS`` boxes
        """
        n = boxes.shape[0]
        if n > _kernels.MAX_ITEMS:
            raise ValueError(f"a tree holds at most {_kernels.MAX_ITEMS} items, got {n}")
        keys = _layout.morton_keys(boxes, _layout.world(boxes, self.max_depth), scratch)
        order, keys = sorted_keys(keys, 2 * _kernels.MAX_DEPTH, scratch)
        like = np.empty(0, _kernels.index_type(2 * n))  # int32 ranges while they fit
        return order, _layout.split(keys.view(np.int64), self.leaf_size, like)

    def _built_ids(self) -> np.ndarray:
        """The built items' ids, in slot order (made, when the tree stores none)."""
        return self._ids if len(self._ids) == self._n else np.arange(self._n, dtype=np.int64)

    def _read_all(self) -> None:
        """Before Python reads the built arrays as a whole: every block of them checked."""
        if self._watch is not None:
            self._watch.check(self._nodes, self._boxes, self._ids)

    def _pack(self) -> None:
        """What every query and diff passes the kernels, built again whenever it changes: after
        a load, when the insert buffer grows or its count changes, on a new tombstone; and the
        kernels' compiled code for its types, looked up once a build for each of its two
        (a tree with no edits has a walk of its own)."""
        watch, inserts = self._watch, self._inserts
        edits = None
        if self._n_dead or self._n_extra:
            dead = self._dead.at if self._dead is not None else _NONE_DEAD  # read only with HAS_DEAD
            edits = (dead, inserts.boxes, inserts.ids, inserts.gone, self._n_extra, self._horizon)
        self._arrays = _walk.pack(
            self._nodes,
            self._boxes,
            None if self._ids is _SLOT_IDS else self._ids,
            edits,
            None if watch is None else (watch.marks, watch.pending, self._places),
        )
        self._flags = (_walk.HAS_DEAD if self._n_dead else 0) | (_walk.X_ORDER if self.x_order else 0)
        walks = self._walks.get(edits is None)
        if walks is None:  # a build's trees, copies too, have two packs' types: with edits and without
            point, size = (0.0,) * 4, 0.0
            walks = self._walks[edits is None] = (
                _compiled(_walk.query, self._arrays, self._flags, *point, size),
                _compiled(_walk.diff, self._arrays, self._flags, *point, size, *point, size),
            )
        self._query, self._diff = walks

    def _links(self) -> np.ndarray:
        """(m, 4) int64 ``item_lo, item_hi, child_lo, child_hi`` unpacked from the node records."""
        packed = self._nodes.view(np.int64)[:, [_kernels.ITEMS, _kernels.CHILDREN]]
        return np.column_stack(
            [packed[:, 0] & 0xFFFFFFFF, packed[:, 0] >> 32, packed[:, 1] & 0xFFFFFFFF, packed[:, 1] >> 32]
        )

    def _built_lookup(self) -> Lookup:
        """Where each built id lies: made from the ids at the first look-up."""
        if self._lookup is None:
            if self._watch is not None:  # the ids, which the lookup reads whole: not the nodes and boxes
                self._watch.check(self._ids)
            self._lookup = Lookup.of(self._ids)
        return self._lookup

    def _locate_built(self, item_id: int) -> int | None:
        pos = self._built_lookup().find(item_id)
        return pos if pos is not None and (self._dead is None or self._dead.at[pos] < self._horizon) else None

    @property
    def _horizon(self) -> int:
        """The stamp of this tree's clock: a slot or row stamped at or past it was removed at or
        before it, so this tree sees it removed (``_Tombstones``)."""
        return _NEVER - self._clock

    def _live_mask(self) -> np.ndarray:
        """Which built slots this tree holds (a bool a slot)."""
        assert self._dead is not None
        return self._dead.at < self._horizon

    def _extra_live(self) -> np.ndarray:
        """Which of the insert buffer's rows this tree sees hold a live item (a bool a row)."""
        return self._inserts.gone[: self._n_extra] < self._horizon

    def _tombstone(self, index: int) -> None:
        """Mark built item ``index`` removed, at the next tick of the shared clock: copies made
        before it do not see it."""
        dead = self._tick()
        dead.at[index] = self._horizon
        self._n_dead += 1

    def _tick(self) -> _Tombstones:
        """Advance the clock that the tombstones and the insert buffer's removals share; the
        tombstones. A tree edited after another shared its clock (a fork), or with the clock
        run out, first makes tombstones of its own, and an insert buffer too unless no tick
        was ever written in its own (those it sees removed marked at tick 0: before every clock)."""
        dead, inserts = self._dead, self._inserts
        if dead is None or self._clock != dead.tip or dead.tip == _LAST_TICK:
            at = np.zeros(self._n, np.uint16)
            if dead is not None:
                at[~self._live_mask()] = _NEVER
            if dead is not None or inserts.ticks is not None:  # ticks of another clock in it
                inserts = self._own_inserts(len(inserts.ids))
            dead = self._dead = _Tombstones(at)
            self._clock = 0
        assert inserts.ticks in (None, dead), "a buffer holds the ticks of one clock"
        inserts.ticks = dead
        dead.tip = self._clock = dead.tip + 1
        return dead

    def _locate(self, item_id: int) -> tuple[str, int] | None:
        index = self._extra_index.get(item_id)
        if index is not None:
            return "extra", index
        pos = self._locate_built(item_id)
        return None if pos is None else ("built", pos)

    def _require(self, item_id: int) -> tuple[str, int]:
        where = self._locate(item_id)
        if where is None:
            raise KeyError(f"id {item_id} is not in the tree")
        return where

    def _append_extra(self, item_id: int, box: tuple[float, float, float, float]) -> None:
        """Buffer ``item_id`` in a new row: written in place when no other tree wrote past this
        one's rows (a copy made before sees none of it), else into a buffer of its own."""
        k, inserts = self._n_extra, self._inserts
        if k != inserts.count or k == len(inserts.ids):
            inserts = self._own_inserts(2 * k)
        inserts.boxes[k], inserts.ids[k], inserts.gone[k] = box, item_id, 0
        inserts.count = self._n_extra = k + 1
        self._extra_index = self._extra_index.set(item_id, k)
        self._pack()

    def _remove_extra(self, item_id: int, index: int) -> None:
        """Mark buffered row ``index`` removed, at the next tick: copies made before still see it."""
        self._tick()
        self._inserts.gone[index] = self._horizon
        self._extra_index = self._extra_index.delete(item_id)

    def _own_inserts(self, room: int) -> _Inserts:
        """An insert buffer of this tree's own, of ``room`` rows, holding the rows it sees (those
        removed marked at tick 0: before every clock)."""
        k, old = self._n_extra, self._inserts
        new = self._inserts = _Inserts(max(room, 16))
        new.boxes[:k], new.ids[:k] = old.boxes[:k], old.ids[:k]
        new.gone[:k] = np.where(old.gone[:k] < self._horizon, 0, _NEVER)
        new.count = k
        return new

    def _maybe_compact(self) -> None:
        # Buffered items past ``max_buffered``, or rows (removed ones too: each walk skips them)
        # past 4x it: a tree whose inserts come and go (an overview's bands) rebuilds no sooner
        buffered = len(self._extra_index) > self.max_buffered or self._n_extra > 4 * self.max_buffered
        if buffered or self._n_dead > max(self.max_buffered, self._n // 4):
            self.compact()


class _Inserts:
    """The insert buffer, shared by a tree and its copies: each row's box, id and the stamp of
    the tick at which it was removed (0: it was not) on the clock of ``ticks``, as the
    tombstones'; ``count``: the rows written. A tree sees its first ``_n_extra`` rows: one may
    write the next in place only while no other tree has (``count``)."""

    __slots__ = ("boxes", "count", "gone", "ids", "ticks")

    def __init__(self, rows: int) -> None:
        self.boxes = np.empty((rows, 4), np.float64)
        self.ids = np.empty(rows, np.int64)
        self.gone = np.zeros(rows, np.uint16)
        self.count = 0
        self.ticks: _Tombstones | None = None  # whose clock ``gone``'s ticks are (None: only tick 0s)


class _Tombstones:
    """The built slots removed, shared by a tree and its copies: the tick of the clock at which
    each was removed, stamped as ``_NEVER - tick`` (0: it was not). A tree sees a slot as
    removed when its tick is at or before the tree's clock (its stamp at or past ``_NEVER -
    clock``), so a copy sees what its original had removed when it was made, and not what
    either removes after. Only the tree at the ``tip`` (the last to remove) may add to them:
    trees edited one after another share them, each edit a tick. A slot not removed is 0 so
    that new tombstones are zeroed memory, which the kernel hands out as pages are first
    written: no pass over the n slots (200 MB at 1e8 items) when a tree first removes one."""

    __slots__ = ("at", "tip")

    def __init__(self, at: np.ndarray) -> None:
        self.at, self.tip = at, 0


def _compiled(kernel: Any, *args: object) -> Any:
    """``kernel``'s compiled code for these arguments' types, called without numba's dispatcher.

    The dispatcher works out the types of every argument on every call (~0.3 us of a 1.5 us
    query, the tree's tuple of arrays being most of it); a tree's argument types change only
    when its pack does, so its compiled code is looked up then, and kept by a key of the types
    numba tells apart (working them out took ~0.25 ms a tree: 19 ms to open a document of 19
    trees). ``args`` must have the types of the later calls' arguments. Where numba's
    internals do not offer this, the dispatcher.
    """
    key = (kernel, _types(args))
    entry = _ENTRIES.get(key)
    if entry is not None:
        return entry
    try:
        signature = tuple(kernel.typeof_pyval(arg) for arg in args)
        if signature not in kernel.overloads:
            kernel.compile(signature)
        entry = _ENTRIES[key] = kernel.overloads[signature].entry_point
        return entry
    except Exception:  # numba internals (typeof_pyval, overloads, entry_point) moved: dispatch
        return kernel


_NEVER = np.iinfo(np.uint16).max  # after every tick: stamps are ``_NEVER - tick``, 0 for never
_LAST_TICK = _NEVER - 1
_NONE_DEAD = np.zeros(1, np.uint16)  # what the kernels get for a tree with no tombstones: never read
_SLOT_IDS = np.empty(0, np.int64)  # the ids of a tree whose ids are its slots: stored nowhere
_ENTRIES: dict[tuple, Any] = {}  # (kernel, _types(args)): its compiled code


def _types(value: object) -> object:
    """What numba's type of ``value`` depends on: an array's element type, dimensions, layout,
    whether it is read-only and aligned; a tuple's members'; else the Python type."""
    if isinstance(value, np.ndarray):
        flags = value.flags
        layout = "C" if flags.c_contiguous else "F" if flags.f_contiguous else "A"
        return (value.dtype.str, value.ndim, layout, flags.writeable, flags.aligned)
    if isinstance(value, tuple):
        return tuple(_types(v) for v in value)
    return type(value)
