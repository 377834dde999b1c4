"""Edits against a dict model: hypothesis drives insert/remove/update, the tree must agree."""

import tracemalloc

import numpy as np
import oracle
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from spatial import QuadTree, quadtree
from spatial._lookup import Lookup

coordinate = st.floats(-1_000, 1_000, allow_nan=False).map(lambda v: round(v, 1))
extent = st.sampled_from([0.0, 0.5, 3.0, 40.0, 400.0])


@st.composite
def boxes(draw):
    x0, y0 = draw(coordinate), draw(coordinate)
    return (x0, y0, x0 + draw(extent), y0 + draw(extent))


class TreeAgainstDict(RuleBasedStateMachine):
    """A dict id -> box is the model; queries and diffs of the tree must match it after every step."""

    @initialize(
        items=st.lists(boxes(), max_size=300),
        leaf_size=st.sampled_from([1, 4, 32]),
        buffered=st.sampled_from([12, 100]),
        mapped=st.booleans(),
    )
    def load(self, items, leaf_size, buffered, mapped):
        self.model = dict(enumerate(items))
        array = np.array(items, dtype=np.float64).reshape(-1, 4)
        self.tree = QuadTree.bulk_load(array, leaf_size=leaf_size)
        self.origin = None  # the tree as made over arrays (from_arrays), if it was: never edited
        if mapped:  # over arrays made elsewhere (a file's), as a document's tree is
            self.origin = QuadTree.from_arrays(self.tree.to_arrays())
            self.tree = QuadTree.from_arrays(self.tree.to_arrays())
        self.tree.max_buffered = buffered  # compact often, so rebuilds happen inside the runs, or not
        self.next_id = len(items)
        self.copies: list[tuple[QuadTree, dict]] = []  # earlier versions: edits since never reach them

    @rule(box=boxes())
    def insert(self, box):
        self.tree.insert(self.next_id, box)
        self.model[self.next_id] = box
        self.next_id += 1

    @precondition(lambda self: self.model)
    @rule(data=st.data())
    def remove(self, data):
        item_id = data.draw(st.sampled_from(sorted(self.model)))
        self.tree.remove(item_id)
        del self.model[item_id]

    @precondition(lambda self: self.model)
    @rule(data=st.data(), box=boxes())
    def update(self, data, box):
        item_id = data.draw(st.sampled_from(sorted(self.model)))
        self.tree.update(item_id, box)
        self.model[item_id] = box

    @rule(item_id=st.integers(-5, 5_000))
    def missing_ids_raise_key_error(self, item_id):
        if item_id in self.model:
            assert self.tree.get(item_id) == self.model[item_id]
            with pytest.raises(ValueError, match="already in the tree"):
                self.tree.insert(item_id, (0, 0, 1, 1))
        else:
            with pytest.raises(KeyError):
                self.tree.remove(item_id)
            with pytest.raises(KeyError):
                self.tree.update(item_id, (0, 0, 1, 1))

    @rule()
    def compact(self):
        self.tree.compact()

    @rule(by_id=st.booleans())
    def made_again_from_its_edits(self, by_id):
        """A tree's edits as arrays (``edits``), made again at once over the arrays it was made
        from (``with_edits``: an open from a document's saved edits), make the same tree, the
        slots removed given as such or by id. One that rebuilt itself since cannot say them."""
        if self.origin is None or not self.tree._mapped:
            with pytest.raises(ValueError, match="rebuilt itself"):
                self.tree.edits()
            return
        edits = self.tree.edits()
        if by_id:
            edits["removed"] = self.origin._built_ids()[edits.pop("dead")]
        self.tree = self.origin.with_edits(edits)

    @rule()
    def copy(self):
        """A copy is a snapshot: later edits of the tree (removals most of all: a mask made
        or shared) never show in it."""
        self.copies = [*self.copies[-2:], (self.tree.copy(), dict(self.model))]

    @precondition(lambda self: self.copies)
    @rule(data=st.data(), box=boxes())
    def edit_a_copy(self, data, box):
        """A copy edited as well (a fork of the tree's edits): its removals and moves never show
        in the tree, nor the tree's in it, before or after."""
        copy, model = data.draw(st.sampled_from(self.copies))
        if model:
            copy.remove(gone := data.draw(st.sampled_from(sorted(model))))
            del model[gone]
        if model:
            copy.update(moved := data.draw(st.sampled_from(sorted(model))), box)
            model[moved] = box

    @invariant()
    def agrees_with_the_model(self):
        self.tree._check()
        assert len(self.tree) == len(self.model)
        ids = np.array(sorted(self.model), dtype=np.int64)
        array = np.array([self.model[i] for i in ids.tolist()], dtype=np.float64).reshape(-1, 4)
        for old, new in (((-50, -50, 50, 50), (-20, -40, 80, 60)), ((-900, 0, 0, 900), (0, 0, 900, 900))):
            assert set(self.tree.query(new).tolist()) == oracle.query(array, ids, new)
            entered, left = self.tree.diff(old, new)
            before, after = oracle.query(array, ids, old), oracle.query(array, ids, new)
            assert set(entered.tolist()) == after - before
            assert set(left.tolist()) == before - after
        assert set(self.tree.query((-1e4, -1e4, 1e4, 1e4), min_size=3.0).tolist()) == oracle.query(
            array, ids, (-1e4, -1e4, 1e4, 1e4), 3.0
        )
        union = (*array[:, :2].min(axis=0), *array[:, 2:].max(axis=0)) if len(array) else None
        assert self.tree.bounds == (tuple(map(float, union)) if union else None)  # exact after removals too
        for copy, model in self.copies:
            copy._check()
            assert set(copy.query((-1e4, -1e4, 1e4, 1e4)).tolist()) == set(model)
            assert {i: copy.get(i) for i in model} == model


TestTreeAgainstDict = TreeAgainstDict.TestCase


def test_copy_is_independent_of_later_edits():
    tree = QuadTree.bulk_load([[0, 0, 1, 1], [5, 5, 6, 6]])
    snapshot = tree.copy()
    tree.remove(0)
    tree.insert(7, (0, 0, 2, 2))
    tree.update(1, (100, 100, 101, 101))
    assert sorted(snapshot.query((0, 0, 10, 10)).tolist()) == [0, 1]
    assert sorted(tree.query((0, 0, 10, 10)).tolist()) == [7]
    snapshot._check()
    tree._check()


def test_a_copy_of_a_tree_with_tombstones_costs_nothing_per_item():
    """Each of the service's edits copies its tree: a copy must not copy 1 or 2 bytes an item
    (100 MB an edit at 1e8 items), however many items were removed before it."""
    n = 1_000_000
    rng = np.random.default_rng(1)
    tree = QuadTree.bulk_load(np.column_stack([xy := rng.uniform(0, 1e4, (n, 2)), xy + 1]))
    for i in range(0, 2_000, 2):
        tree.update(i, (0, 0, 1, 1))
    for i in range(1, 50, 2):
        tree.remove(i)
    tracemalloc.start()
    try:
        for _ in range(5):
            tree = tree.copy()
            tree.remove(int(rng.integers(2_000, n)))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < n // 2, f"five copies and removals allocated {peak:,} bytes"  # one mask is n B


def test_tombstones_stay_right_when_their_clock_runs_out(monkeypatch):
    """Past the last tick a tree renumbers its tombstones in an array of its own; copies made
    before keep seeing theirs."""
    monkeypatch.setattr(quadtree, "_LAST_TICK", 3)
    boxes = np.array([[i, 0, i + 1, 1] for i in range(10)], dtype=np.float64)
    tree, copies = QuadTree.bulk_load(boxes), []
    for i in range(9):
        copies.append((tree.copy(), set(range(i, 10))))
        tree.remove(i)
    copies.append((tree, {9}))
    for copy, live in copies:
        assert set(copy.query((0, 0, 10, 1)).tolist()) == live
        copy._check()


def test_edits_accumulate_into_a_rebuild_without_a_wrong_answer():
    rng = np.random.default_rng(0)
    boxes = np.column_stack([xy := rng.uniform(0, 1000, (5_000, 2)), xy + 5])
    tree = QuadTree.bulk_load(boxes)
    model = {i: tuple(b) for i, b in enumerate(boxes.tolist())}
    for step in range(3_000):
        item_id = int(rng.integers(0, 5_000))
        new = rng.uniform(0, 1000, 2)
        box = (new[0], new[1], new[0] + 5, new[1] + 5)
        tree.update(item_id, box)
        model[item_id] = box
        if step % 500 == 0:
            ids = np.array(sorted(model))
            array = np.array([model[i] for i in ids.tolist()])
            assert set(tree.query((100, 100, 400, 300)).tolist()) == oracle.query(
                array, ids, (100, 100, 400, 300)
            )
    assert len(tree._extra_index) <= tree.max_buffered, "the insert buffer was never merged"
    assert tree._n_extra <= 4 * tree.max_buffered, "the removed rows of the buffer were never dropped"
    tree._check()


def _grid(n: int) -> np.ndarray:
    xy = np.column_stack([np.arange(n) % 100, np.arange(n) // 100]).astype(np.float64) * 10
    return np.column_stack([xy, xy + 5])


def _agrees(tree: QuadTree, boxes: dict[int, tuple]) -> None:
    ids = np.array(sorted(boxes))
    array = np.array([boxes[i] for i in ids.tolist()])
    for rect in ((0, 0, 300, 300), (-1, -1, 2000, 2000), (250, 40, 260, 900)):
        assert set(tree.query(rect).tolist()) == oracle.query(array, ids, rect)
    tree._check()


def test_inserts_rebuild_the_tree_once_the_buffer_passes_256_plus_n_over_512():
    n = 10_240  # the documented threshold (docs/how-it-works.md): 256 + 10,240 / 512 = 276 buffered inserts
    tree = QuadTree.bulk_load(_grid(n))
    boxes = dict(enumerate(map(tuple, _grid(n).tolist())))
    for k in range(276):
        boxes[n + k] = (k * 3.0, -50.0, k * 3.0 + 2, -48.0)
        tree.insert(n + k, boxes[n + k])
    assert tree._n_extra == 276 and tree._n == n  # at the threshold: still buffered
    _agrees(tree, boxes)
    boxes[n + 276] = (0.0, -60.0, 1.0, -59.0)
    tree.insert(n + 276, boxes[n + 276])
    assert tree._n_extra == 0 and tree._n == n + 277  # past it: rebuilt from every live item
    _agrees(tree, boxes)


def test_removals_rebuild_the_tree_once_tombstones_pass_a_quarter_of_it():
    n = 10_240  # a quarter: 2,560 tombstones (more than the 276 the insert buffer allows)
    tree = QuadTree.bulk_load(_grid(n))
    boxes = dict(enumerate(map(tuple, _grid(n).tolist())))
    for item_id in range(2_560):
        tree.remove(item_id)
        del boxes[item_id]
    assert tree._n_dead == 2_560 and tree._n == n  # at a quarter: tombstones only
    _agrees(tree, boxes)
    tree.remove(2_560)
    del boxes[2_560]
    assert tree._n_dead == 0 and tree._n == n - 2_561  # past it: rebuilt without them
    _agrees(tree, boxes)


def test_one_removal_and_a_buffered_insert_leaving_the_view_answer_exactly():
    tree = QuadTree.bulk_load(_grid(1_000))
    boxes = dict(enumerate(map(tuple, _grid(1_000).tolist())))
    tree.remove(0)  # exactly one tombstone: queries must start honouring them
    del boxes[0]
    _agrees(tree, boxes)
    tree.insert(5_000, (20.0, 20.0, 22.0, 22.0))  # buffered, inside the old view only
    boxes[5_000] = (20.0, 20.0, 22.0, 22.0)
    entered, left = tree.diff((0, 0, 30, 30), (100, 0, 130, 30))
    ids = np.array(sorted(boxes))
    array = np.array([boxes[i] for i in ids.tolist()])
    before, after = oracle.query(array, ids, (0, 0, 30, 30)), oracle.query(array, ids, (100, 0, 130, 30))
    assert 5_000 in set(left.tolist()) and set(left.tolist()) == before - after
    assert set(entered.tolist()) == after - before


def test_an_item_exactly_min_size_wide_is_kept():
    tree = QuadTree.bulk_load([[0, 0, 4, 1], [10, 0, 11, 3.999], [20, 0, 23, 3]])
    assert sorted(tree.query((-1, -1, 30, 30), min_size=4.0).tolist()) == [0]  # max(w, h) >= min_size
    assert sorted(tree.diff((50, 50, 60, 60), (-1, -1, 30, 30), min_size=4.0)[0].tolist()) == [0]


def test_buffered_rows_stay_right_when_the_clock_runs_out(monkeypatch):
    """Inserted items removed or moved across the clock's last tick: the buffer's rows are
    renumbered with the tombstones; copies made before keep seeing theirs."""
    monkeypatch.setattr(quadtree, "_LAST_TICK", 3)
    tree, copies = QuadTree.bulk_load(np.array([[0, 0, 1, 1]], dtype=np.float64)), []
    for i in range(1, 10):
        tree.insert(i, (i, 0, i + 1, 1))
    for i in range(1, 9):
        copies.append((tree.copy(), {0, *range(i, 10)}, {j: (j, 0, j + 1, 1) for j in range(i + 1, 10)}))
        tree.remove(i)
        if i + 1 < 10:
            tree.update(i + 1, (i + 1, 0, i + 2, 1))  # moved in place: a row removed, one added
    copies.append((tree, {0, 9}, {9: (9, 0, 10, 1)}))
    for copy, live, boxes in copies:
        copy._check()
        assert set(copy.query((0, 0, 10, 1)).tolist()) == live
        assert {j: copy.get(j) for j in boxes} == {j: tuple(map(float, b)) for j, b in boxes.items()}


def test_a_copy_of_a_tree_with_buffered_inserts_costs_nothing_per_insert():
    """Each of the service's edits copies its tree: a copy must not copy its insert buffer
    (40 bytes an insert: ~16 MB an edit with the 392k edits a 1e8-item document buffers)."""
    tree = QuadTree.bulk_load(np.array([[0, 0, 1, 1]], dtype=np.float64))
    tree.max_buffered = 10**6
    for i in range(1, 50_001):
        tree.insert(i, (i % 1000, 0, i % 1000 + 1, 1))
    tracemalloc.start()
    try:
        for i in range(1, 6):
            tree = tree.copy()
            tree.update(i, (0, 5, 1, 6))  # a row removed (a tick), one added
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 100_000, f"five copies and moves allocated {peak:,} bytes"  # the buffer is 2 MB


def test_a_builds_edits_look_its_compiled_walks_up_once_whatever_their_count(monkeypatch):
    """Looking a walk's compiled code up types the tree's pack (~13 us, where an insert costs
    ~3): a build looks up its query's and diff's once for each of its two packs, without edits
    and with them, however many edits and copies follow; a new build looks them up again."""
    looked_up = []
    compiled = quadtree._compiled
    monkeypatch.setattr(quadtree, "_compiled", lambda *args: looked_up.append(args[0]) or compiled(*args))
    boxes = np.array([[i, 0, i + 1, 1] for i in range(100)], dtype=np.float64)
    tree = QuadTree.bulk_load(boxes)
    tree.max_buffered = 10**6
    assert looked_up[-2:] == [quadtree._walk.query, quadtree._walk.diff]  # the pack without edits
    looked_up.clear()
    for i in range(100, 150):
        tree = tree.copy()
        tree.insert(i, (i, 0, i + 1, 1))
        tree.remove(i - 100)  # a built item's tombstone
        tree.update(i, (i, 5, i + 1, 6))
    assert len(looked_up) == 2  # and of the pack with edits, once
    assert sorted(tree.query((0, 0, 200, 10)).tolist()) == list(range(50, 150))
    tree.compact()
    assert len(looked_up) == 4  # a new build, the types of its arrays looked up afresh


@given(
    ids=st.lists(st.integers(-(2**40), 2**40) | st.integers(-20, 60), unique=True, max_size=80),
    asked=st.lists(st.integers(-(2**40), 2**40) | st.integers(-30, 70), max_size=40),
    identity=st.booleans(),
)
def test_ids_looked_up_together_are_where_one_at_a_time_finds_them(ids, asked, identity):
    """``find_many`` (a tree's removals made again at an open) answers as ``find`` does, id by
    id, whichever way the lookup is kept: dense, sorted, or ids that are their slots."""
    if identity:
        lookup = Lookup.identity(len(ids))
        asked = [*asked, *range(len(ids))]
    else:
        lookup = Lookup.of(np.array(ids, np.int64))
        asked = [*asked, *ids]
    found = [-1 if (pos := lookup.find(i)) is None else pos for i in asked]
    assert lookup.find_many(np.array(asked, np.int64)).tolist() == found


def test_edits_made_again_refuse_an_id_the_tree_never_held():
    tree = QuadTree.from_arrays(QuadTree.bulk_load(np.array([[0, 0, 1, 1], [2, 2, 3, 3.0]])).to_arrays())
    none = np.empty(0, np.int64)
    with pytest.raises(KeyError, match="id 7 is not in the tree"):
        tree.with_edits({"removed": np.array([1, 7]), "ids": none, "boxes": np.empty((0, 4))})
    assert tree.with_edits({"removed": np.array([1]), "ids": none, "boxes": np.empty((0, 4))}).query(
        (0, 0, 9, 9)
    ).tolist() == [0]
