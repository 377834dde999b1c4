"""The overview against brute force: at every band, every item is either big enough to be drawn
itself or inside an aggregate of that band whose box contains its box; the counts add up; and
edits keep both true (a hypothesis state machine against a dict of boxes)."""

import functools
import math
import tempfile
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule

from app.table import scratch_array
from spatial import MemoryBudget, QuadTree, scenes
from spatial._kernels import cell_runs, rectangle_groups, run_cells
from spatial.overview import RULES, TILE, Overview, band_for_size
from spatial.overview._build import _Boxes, _by_columns, _cell_order, _group_order, _group_union

pytestmark = pytest.mark.usefixtures("scratch_in_files")  # small inputs, mapped paths

EVERYTHING = (-1e300, -1e300, 1e300, 1e300)


def _sizes(boxes: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):  # a side of 3.4e308 is inf, as the index sizes it
        return np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])


def _check_band(view: Overview, boxes: np.ndarray, band: int, z: np.ndarray | None = None) -> None:
    """Brute force over one band (freshly built): membership, each box its members' union,
    counts, cover and parents."""
    members = np.flatnonzero(_sizes(boxes) < view.threshold(band))
    aggs = view.query(band, EVERYTHING)
    got, count, cover, _, top = view.rows(band, aggs)
    assert int(count.sum()) == len(members), f"band {band}: counts add up to the members"
    assert ((cover >= 0) & (cover <= 1)).all()
    owner = np.array([view.aggregate_of(int(i), band) for i in members], np.int64)
    where = np.searchsorted(np.sort(aggs), owner)
    box = dict(zip(aggs.tolist(), got.tolist(), strict=True))
    assert np.isin(owner, aggs).all(), f"band {band}: an item's aggregate is not in the band"
    held = np.array([box[k] for k in owner.tolist()]).reshape(-1, 4)
    mine = boxes[members]
    inside = (held[:, :2] <= mine[:, :2]).all(axis=1) & (mine[:, 2:] <= held[:, 2:]).all(axis=1)
    assert inside.all(), f"band {band}: item {members[~inside][:1]} lies outside its aggregate"
    union = np.full((len(aggs), 4), np.inf)  # a fresh build's boxes are their members' union
    union[:, 2:] = -np.inf
    for k in range(2):
        np.minimum.at(union[:, k], where, mine[:, k])
        np.maximum.at(union[:, k + 2], where, mine[:, k + 2])
    assert (union == got[np.argsort(aggs)]).all(), (
        f"band {band}: an aggregate's box is not its members' union"
    )
    if z is not None:
        highest = np.full(len(aggs), np.iinfo(np.int64).min)
        np.maximum.at(highest, where, z[members])
        assert (highest == top[np.argsort(aggs)]).all(), (
            f"band {band}: an aggregate's z is not its members' top"
        )
    per_agg = np.bincount(where, minlength=len(aggs)) if len(aggs) else np.empty(0)
    assert (per_agg == count[np.argsort(aggs)]).all(), f"band {band}: an aggregate's count is not its members"
    for k in view.query(band, (boxes[:, 0].min(), boxes[:, 1].min(), boxes[:, 2].max(), boxes[:, 3].max()))[
        :50
    ]:
        parent = view._row(band, int(k))[5]
        if band < view.hi:
            up = view.get(band + 1, parent).box
            mine_box = view.get(band, int(k)).box
            assert (
                up[0] <= mine_box[0]
                and up[1] <= mine_box[1]
                and mine_box[2] <= up[2]
                and mine_box[3] <= up[3]
            )


@pytest.mark.parametrize(
    "scene",
    [
        lambda: scenes.long_document(pages=12, seed=1),
        lambda: scenes.whiteboard(n=8000, seed=2, clusters=12),
        lambda: scenes.uniform(n=5000, seed=3),
    ],
    ids=["document", "whiteboard", "uniform"],
)
@pytest.mark.parametrize("rule", RULES)
def test_every_item_is_drawn_or_inside_an_aggregate_at_every_band(scene, rule):
    boxes, kinds = scene()
    z = np.arange(len(boxes)) % 5
    view = Overview.build(boxes, kinds, z, rule=rule)
    assert view.lo <= view.hi
    for band in range(view.lo, view.hi + 1):
        _check_band(view, boxes, band, z)
    top = view.rows(view.hi, view.query(view.hi, EVERYTHING))[1]
    assert len(top) <= 4 and top.sum() == len(boxes)  # the top band sums the whole scene up in a few


def test_words_merge_into_line_runs_and_lines_into_blocks():
    line = [[10 * i, 0, 10 * i + 8, 4] for i in range(10)]  # words of 8 units, 2 apart
    words = np.array(line + [[x0, y0 + 40, x1, y1 + 40] for x0, y0, x1, y1 in line])
    view = Overview.build(words)
    lines = view.rows(4, view.query(4, EVERYTHING))  # 16-unit cells: gaps under a cell close up
    assert sorted(map(tuple, lines[0].tolist())) == [(0, 0, 98, 4), (0, 40, 98, 44)]
    assert lines[1].tolist() == [10, 10]
    block = view.rows(5, view.query(5, EVERYTHING))  # 32-unit cells: the lines are in adjacent rows
    assert block[0].tolist() == [[0, 0, 98, 44]] and block[1].tolist() == [20]
    assert block[2][0] == pytest.approx(20 * 32 / (98 * 44))  # cover: the words' area over the box's


def test_the_kind_is_the_largest_elements_and_z_the_highest():
    boxes = np.array([[0, 0, 60, 80], [5, 5, 9, 7], [10, 5, 14, 7], [20, 5, 24, 7]])
    view = Overview.build(boxes, kinds=[0, 1, 1, 1], z=[0, 3, 3, 7])
    agg = view.get(7, int(view.query(7, EVERYTHING)[0]))
    assert (agg.count, agg.kind, agg.z) == (4, 0, 7)


def test_an_item_whose_area_overflows_adds_no_area_and_gives_no_kind():
    """An item 1e200 on a side has an area past float64's: it counts in its aggregate, but
    adds no area to it, and the items under it keep their kind."""
    boxes = np.array([[0, 0, 1e200, 1e200], [1, 1, 2, 2], [3, 3, 4, 5]])
    view = Overview.build(boxes, kinds=[7, 1, 1], z=[0, 0, 0])
    agg = view.get(view.hi, int(view.query(view.hi, EVERYTHING)[0]))
    assert (agg.count, agg.kind) == (3, 1) and view.to_arrays()[f"{view.hi}.area"].tolist() == [3.0]


def _cells(columns: tuple[int, int], rows: tuple[int, int]) -> st.SearchStrategy:
    return st.lists(st.tuples(st.integers(*columns), st.integers(*rows)), max_size=300)


# Cells a float centre gives exactly, their spans: past 64 bits; keys of 64 bits with cells of
# 32; keys of 32 bits with cells of 64; both of 32
_CELLS = st.one_of(
    _cells((-(2**50), 2**50), (-(2**50), 2**50)),
    _cells((-(2**30), 2**30), (-(2**30), 2**30)),
    _cells((0, 2**32 - 1), (0, 0)),
    _cells((-3, 3), (-3, 3)),
)


@given(cells=_CELLS, split=st.integers(0, 300))
def test_cells_sort_by_row_then_column_as_lexsort_does(cells, split):
    """The build's radix sort of cells is ``np.lexsort``'s order, ties in place, spans any
    size, and the cells it gives back are the cells in that order. Each element's box is the
    point ``cell + 0.25`` (its cell at origin 0, cells 1 wide), the first ``split`` from the
    band below's, the rest an item's."""
    cx, cy = (np.array([c[k] for c in cells], np.int64) for k in (0, 1))
    points = np.column_stack([cx, cy, cx, cy]).astype(np.float64) + 0.25
    split = min(split, len(points))
    items = np.concatenate([np.full((3, 4), 9.0), points[split:]])  # items not joining here too
    boxes = _Boxes(points[:split], items, np.arange(3, len(items)))
    expected = np.lexsort((cx, cy))
    order, cells, dtype = _cell_order(boxes, 0.0, 0.0, 0.5)
    sx, sy = _each_cell(cells, dtype)
    assert (order == expected).all() and (sx == cx[expected]).all() and (sy == cy[expected]).all()


def _each_cell(cells: tuple, dtype: type) -> tuple[np.ndarray, np.ndarray]:
    """The sorted cells' columns and rows, read by the runs' kernels: each cell a run of its own
    (a step of more than -1 columns, or a new tile of 1)."""
    run = np.empty(max(len(cells[0]), len(cells[2])), np.int64)
    runs = cell_runs(*cells, -1, 1, run, 0, np.array([-1, 0, 0], np.int64))
    sx, last, sy = (np.empty(runs, dtype) for _ in range(3))
    run_cells(*cells, run, 0, -1, sx, last, sy)
    assert (sx == last).all()
    return sx, sy


@given(
    cells=_CELLS,
    gap=st.integers(0, 1),
    tile=st.sampled_from([1, 8]),
    keyed=st.booleans(),
    step=st.integers(1, 4),
)
def test_runs_of_sorted_cells_start_where_a_row_a_gap_or_a_tile_begins(cells, gap, tile, keyed, step):
    """Each sorted cell's run (read from the columns and rows, or from keys ``row * width +
    column``) against a plain pass: a run starts at a new row, a step of more than ``gap``
    columns, or a new tile of ``tile`` columns; each run's first and last column and row.
    Both passes go a ``step`` of cells at a time (as over keys in a file), each carrying on
    from the cell before."""
    cx, cy = (np.array([c[k] for c in cells], np.int64) for k in (0, 1))
    at = np.lexsort((cx, cy))
    cx, cy = cx[at], cy[at]
    starts = [
        i == 0 or cy[i] != cy[i - 1] or cx[i] - cx[i - 1] > gap or cx[i] // tile != cx[i - 1] // tile
        for i in range(len(cx))
    ]
    expected = np.cumsum(starts) - 1
    none = np.empty(0, np.int64)
    x0, y0 = (int(c.min()) if len(c) else 0 for c in (cx, cy))
    width = int(cx.max()) - x0 + 1 if len(cx) else 1
    if keyed and width * (int(cy.max()) - y0 + 1 if len(cy) else 1) < 2**64:
        key = ((cy - y0).astype(np.uint64) * np.uint64(width) + (cx - x0).astype(np.uint64)).astype(np.uint64)
        sorted_cells: tuple = (none, none, key, np.uint64(width), x0, y0)
    else:
        sorted_cells = (cx, cy, np.empty(0, np.uint64), np.uint64(0), 0, 0)
    run, last, runs = np.empty(len(cx), np.int64), np.array([-1, 0, 0], np.int64), 0
    for lo in range(0, len(cx), step):
        runs = cell_runs(*sorted_cells, gap, tile, run[lo : lo + step], lo, last)
    assert runs == len(set(expected.tolist())) and (run == expected).all()
    rx0, rx1, ry = (np.empty(runs, np.int64) for _ in range(3))
    for lo in range(0, len(cx), step):
        run_cells(*sorted_cells, run[lo : lo + step], lo, run[lo - 1] if lo else -1, rx0, rx1, ry)
    first = np.flatnonzero(starts)
    last = np.append(first[1:], len(cx))[: len(first)] - 1
    assert (rx0 == cx[first]).all() and (rx1 == cx[last]).all() and (ry == cy[first]).all()


_COORD = (
    st.floats(allow_nan=False, allow_infinity=False)
    | st.floats(-1e-307, 1e-307)
    | st.sampled_from([0.0, -0.0, 1e308, 1.7e308, -1.7e308])
)


@given(corners=st.lists(st.tuples(_COORD, _COORD, _COORD, _COORD), min_size=1, max_size=40))
def test_each_element_s_cell_is_numpy_s_of_its_centre(corners):
    """The cells the build sorts by are numpy's ``floor(((lo * 0.5 + hi * 0.5) * 0.5 - origin *
    0.5) / half)`` of each box, to the bit, in every band, at any scale: the band's elements are
    made from them, so an aggregate's members stay today's."""
    boxes = np.array([[min(a, c), min(b, d), max(a, c), max(b, d)] for a, b, c, d in corners])
    view = Overview.build(boxes)
    ox, oy = boxes[:, 0].min(), boxes[:, 1].min()
    for level in range(view.lo, view.hi + 1):
        half = math.ldexp(1.0, level - 1)
        elements = _Boxes(boxes[:3], boxes, np.arange(3, len(boxes)))
        at = (ox * 0.5, oy * 0.5, half)
        x0, y0, _, _ = elements.cell_range(at)
        for axis, origin, least, kx, ky in ((0, ox, x0, 1, 0), (1, oy, y0, 0, 1)):
            centre = (boxes[:, axis] * 0.5 + boxes[:, axis + 2] * 0.5) * 0.5 - origin * 0.5
            expected = np.floor(centre / half).astype(np.int64)
            got = (
                elements.cell_keys(at, x0, y0, kx, ky, np.empty(len(elements), np.uint64)).view(np.int64)
                + least
            )
            assert (got == expected).all(), (level, axis)
            assert least == expected.min()


_AREAS = st.floats(allow_nan=False) | st.sampled_from([0.0, -0.0, 1.0, math.inf])


@given(members=st.lists(st.tuples(st.integers(0, 5), _AREAS), max_size=200))
def test_aggregates_elements_sort_by_area_as_lexsort_does(members):
    """Each aggregate's elements in the order their reductions take them: by area, ties in
    place (the sum of areas is rounded in that order), groups of any size."""
    owner = np.array([m[0] for m in members], np.int64)
    area = np.array([m[1] for m in members], np.float64)
    count = int(owner.max()) + 1 if len(owner) else 0
    got, starts, placed = _group_order(owner, count, area)
    assert (got == np.lexsort((area, owner))).all()
    assert placed.tobytes() == area[got].tobytes()  # each value beside its place
    assert (starts == np.searchsorted(np.sort(owner), np.arange(count + 1))).all()


_SIDES = st.sampled_from([0.0, -0.0, 1.0, -2.5])


@given(
    members=st.lists(
        st.tuples(st.integers(0, 5), _AREAS, st.tuples(_SIDES, _SIDES, _SIDES, _SIDES), st.booleans()),
        min_size=1,
        max_size=100,
    ),
    one_z=st.booleans(),
)
def test_aggregates_reductions_are_numpys_over_their_elements_in_order(members, one_z):
    """Each aggregate's box, count and z as numpy's ``reduceat`` over its
    elements in ``_group_order``'s order make them, to the sign of a zero: the band below's
    aggregates and the joining items read where they lie, not gathered (an item counts 1 at
    its own z)."""
    owner = np.unique([m[0] for m in members], return_inverse=True)[1].astype(np.int32)
    area = np.array([m[1] for m in members], np.float64)
    boxes = np.array([m[2] for m in members], np.float64)
    held = sum(1 for m in members if m[3])  # the first ``held`` from the band below
    items = np.concatenate([np.full((2, 4), 7.0), boxes[held:]])  # items not joining here too
    values = np.concatenate([np.arange(2, held + 2), np.ones(len(members) - held)]).astype(np.int32)
    z = (np.arange(len(members)) % 7 - 3).astype(np.int32)
    item_z = np.concatenate([[99, 99], z[held:]]).astype(np.int32)  # by item, as the items' boxes
    if one_z:  # a document's items all at one z: a column of that value, held once
        z[held:] = 4
        item_z = np.broadcast_to(np.int32(4), (len(items),))
    count = int(owner.max()) + 1
    order, starts, _ = _group_order(owner, count, area)
    begin = starts[:-1]
    new = np.arange(2, len(items), dtype=np.int32)
    union, sums, top = _group_union(
        order, starts, owner, _Boxes(boxes[:held], items, new), values[:held], z[:held], item_z
    )
    inorder = boxes[order]
    want = np.column_stack(
        [np.minimum.reduceat(inorder[:, k], begin) for k in (0, 1)]
        + [np.maximum.reduceat(inorder[:, k], begin) for k in (2, 3)]
    )
    assert union.tobytes() == want.tobytes()  # the bytes: -0.0 is not 0.0
    assert (sums == np.add.reduceat(values[order], begin)).all()
    assert (top == np.maximum.reduceat(z[order], begin)).all()


@given(
    runs=st.lists(
        st.tuples(st.integers(-3, 3), st.integers(0, 2), st.integers(-2 * TILE, 2 * TILE)), max_size=300
    )
)
def test_runs_over_the_same_columns_in_consecutive_rows_of_a_tile_make_one_rectangle(runs):
    """Each run's rectangle as the sorted columns compared side by side number them: a new
    one wherever the first or last column changes, a row is skipped, or a tile of rows ends."""
    x0 = np.array([r[0] for r in runs], np.int64)
    x1, y = x0 + np.array([r[1] for r in runs], np.int64), np.array([r[2] for r in runs], np.int64)
    by_cols = np.lexsort((y, x1, x0))
    a, b, r = x0[by_cols], x1[by_cols], y[by_cols]
    fresh = np.ones(len(runs), bool)
    fresh[1:] = (
        (a[1:] != a[:-1]) | (b[1:] != b[:-1]) | (r[1:] != r[:-1] + 1) | (r[1:] // TILE != r[:-1] // TILE)
    )
    expected = np.empty(len(runs), np.int64)
    expected[by_cols] = np.cumsum(fresh) - 1
    assert (rectangle_groups(by_cols, x0, x1, y, TILE) == expected).all()


@settings(max_examples=60, deadline=None)
@given(
    runs=st.lists(st.tuples(*[st.sampled_from([-(2**31), -5, 0, 1, 7, 2**31 - 1])] * 3), max_size=60),
    wide=st.booleans(),
    stepped=st.booleans(),
)
def test_runs_by_columns_are_numpys_lexsort(runs, wide, stepped):
    """The runs' order by first column, last column, then row (``_by_columns``): one key a
    run, radix sorted (in files a few keys at a time, with a scratch), where the three fit 64
    bits, numpy's lexsort where they do not (int32 spans of all three): the same order,
    ties in place."""
    x0, x1, y = (np.array([r[k] for r in runs], np.int64 if wide else np.int32) for k in range(3))
    x1 = np.maximum(x0, x1)
    with tempfile.TemporaryDirectory() as directory:
        scratch = functools.partial(scratch_array, Path(directory)) if stepped else None
        with mock.patch("spatial.paging.STEP_BYTES", 24), MemoryBudget(sort_bytes=36).held():
            got = _by_columns(x0, x1, y, scratch)
        assert got.tolist() == np.lexsort((y, x1, x0)).tolist()


def test_band_for_size_is_the_ceiling_of_log2_exactly():
    for size in (1e-300, 0.3, 1.0, 1.5, 2.0, 1000.0, 2.0**40, 1.7e307):
        band = band_for_size(size)
        assert math.ldexp(0.5, band) < size <= math.ldexp(0.5, band) * 2  # halved: 2**1024 overflows


def test_bands_are_clamped_and_need_a_level_of_detail():
    view = Overview.build([[0, 0, 10, 10], [20, 0, 22, 2]])
    assert view.band(0.0) is None and view.band(1e-9) == view.lo and view.band(1e9) == view.hi
    assert Overview.build(np.empty((0, 4))).band(1.0) is None


def test_points_and_extreme_coordinates_are_aggregated():
    boxes = np.array(
        [
            [0, 0, 0, 0],
            [0, 0, 0, 0],
            [1e15, -1e15, 1e15 + 1, -1e15 + 1],
            [-1.7e308, -1.7e308, 1.7e308, 1.7e308],
        ]
    )
    view = Overview.build(boxes)
    for band in range(view.lo, view.hi + 1):
        _check_band(view, boxes, band)
    assert view.aggregate_of(3, view.hi) is None  # a box whose size overflows is always drawn itself


def test_bad_input_is_refused_naming_the_row():
    with pytest.raises(ValueError, match="box 1"):
        Overview.build([[0, 0, 1, 1], [2, 0, 1, 1]])
    with pytest.raises(ValueError, match="one value per box"):
        Overview.build([[0, 0, 1, 1]], kinds=[1, 2])
    with pytest.raises(ValueError, match="rule must be one of rectangles, rows, cells, blobs; got 'grid'"):
        Overview.build([[0, 0, 1, 1]], rule="grid")


BOX = st.tuples(st.floats(-1000, 1000), st.floats(-1000, 1000), st.floats(0, 300), st.floats(0, 300)).map(
    lambda t: (t[0], t[1], t[0] + t[2], t[1] + t[3])
)


class Edits(RuleBasedStateMachine):
    """Inserts, moves and removals against a dict of boxes; the invariants after every step."""

    @initialize(boxes=st.lists(BOX, min_size=1, max_size=60))
    def load(self, boxes):
        self.boxes = dict(enumerate(boxes))
        self.view = Overview.build(np.array(boxes))
        self.next = len(boxes)

    @rule(box=BOX, kind=st.integers(0, 3), z=st.integers(-5, 5))
    def insert(self, box, kind, z):
        self.view = self.view.copy()
        self.view.insert(self.next, box, kind, z)
        self.boxes[self.next] = box
        self.next += 1

    @rule(data=st.data(), box=BOX)
    def move(self, data, box):
        if self.boxes:
            item = data.draw(st.sampled_from(sorted(self.boxes)))
            before, boxes_before = self.view, dict(self.boxes)
            self.view = self.view.copy()
            self.view.remove(item, self.boxes[item])
            self.view.insert(item, box)
            self.boxes[item] = box
            before._check(boxes_before)  # copy on write: the older overview is as it was

    @rule(data=st.data())
    def remove(self, data):
        if self.boxes:
            item = data.draw(st.sampled_from(sorted(self.boxes)))
            self.view = self.view.copy()
            changed = self.view.remove(item, self.boxes.pop(item))
            assert all(self.view.lo <= band <= self.view.hi for band, _ in changed)

    @invariant()
    def every_item_is_drawn_or_inside_its_aggregate(self):
        self.view._check(self.boxes)


Edits.TestCase.settings = settings(max_examples=40, stateful_step_count=25, deadline=None)
test_edits_keep_every_item_inside_its_aggregate = Edits.TestCase


def test_an_overview_from_its_arrays_is_the_same_and_takes_edits():
    boxes, kinds = scenes.whiteboard(n=3000, seed=7, clusters=5)
    arrays = {k: v.copy() for k, v in Overview.build(boxes, kinds).to_arrays().items()}
    view = Overview.from_arrays(arrays)
    for band in range(view.lo, view.hi + 1):
        _check_band(view, boxes, band)
    edited = view.copy()
    edited.remove(0, tuple(boxes[0]))
    with pytest.raises(ValueError, match="edits since its build"):
        edited.to_arrays()
    with pytest.raises(ValueError, match="is missing"):
        Overview.from_arrays({k: v for k, v in arrays.items() if k != "homes"})


@pytest.mark.parametrize("rule", RULES)
def test_the_arrays_built_a_band_at_a_time_are_the_built_overviews(rule):
    """``build_arrays`` (what a snapshot file is written from) yields ``build``'s arrays, the
    same names, types and values, each final when yielded, on a document and on a board of
    extreme coordinates."""
    for boxes, kinds in (scenes.long_document(pages=6, seed=4), scenes.uniform(n=4000, seed=5)):
        if len(kinds) > 2000:
            boxes = boxes * 1e290  # cells far past int32
        z = np.arange(len(boxes)) % 7
        built = Overview.build(boxes, kinds, z, rule=rule).to_arrays()
        # copied as yielded, as a writer writes each then: a yielded array is final
        streamed = {name: array.copy() for name, array in Overview.build_arrays(boxes, kinds, z, rule=rule)}
        assert sorted(streamed) == sorted(built)
        for name, array in built.items():
            assert streamed[name].dtype == array.dtype and np.array_equal(streamed[name], array), name


def test_kinds_and_z_of_one_value_held_once_build_the_same_overview_without_a_copy():
    """A document of one kind (or all at z 0) gives its kinds (or z) as one value broadcast
    (``Looks.of``): the overview built from them is the one built from whole columns, array
    for array, and a band reads them without first copying them whole (``np.take`` would)."""
    import tracemalloc

    from spatial.overview._build import _elements

    boxes, _ = scenes.long_document(pages=6, seed=4)
    n = len(boxes)
    whole = {name: np.full(n, value, np.int32) for name, value in (("kinds", 2), ("z", 5))}
    held = {name: np.broadcast_to(column[:1].copy(), (n,)) for name, column in whole.items()}
    built = Overview.build(boxes, **whole).to_arrays()
    for name, array in Overview.build_arrays(boxes, **held):
        assert array.dtype == built[name].dtype and np.array_equal(array, built[name]), name
    boxes, _ = scenes.uniform(n=20_000, seed=5)
    n, new = len(boxes), np.arange(len(boxes), dtype=np.int32)
    one = np.broadcast_to(np.array([3], np.int32), (n,))
    _elements(None, boxes, new, one, one)  # its kernels compiled (or loaded) first
    tracemalloc.start()
    _elements(None, boxes, new, one, one)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 20 * n + (8 << 10)  # its columns (count, area, z, kind), no copy of one


def test_a_band_built_a_band_at_a_time_is_let_go_once_the_next_is_merged_from_it(monkeypatch):
    """Through ``build_arrays``, a band's arrays (its parents aside, final one band later) are
    held by nothing while the band above is merged from them, but for its counts, areas, z
    and kinds until the band above's elements' own are made from them (once their cells are
    sorted: the areas first, the rest once the areas are summed): the build holds a band's
    elements, never every band."""
    import weakref

    from spatial.overview import _build

    boxes, kinds = scenes.long_document(pages=6, seed=4)
    held: list[tuple[str, weakref.ref]] = []
    merged, ordered, united = _build._merge, _build._group_order, _build._group_union
    merges = []

    def alive() -> list[str]:
        return [name for name, ref in held if ref() is not None]

    def merge(level, *args):
        below = {f"{level - 1}.{column}" for column in ("count", "area", "z", "kind")}
        assert set(alive()) <= below, f"{alive()} held while band {level} is merged"
        merges.append(level)
        return merged(level, *args)

    def group_order(*args):
        below = {f"{merges[-1] - 1}.{column}" for column in ("count", "z", "kind")}
        assert set(alive()) <= below, f"{alive()} held once the elements' areas are made"
        return ordered(*args)

    def group_union(*args):
        below = {f"{merges[-1] - 1}.{column}" for column in ("count", "z")}  # reduced in it
        assert set(alive()) <= below, f"{alive()} held once the elements' areas are summed"
        return united(*args)

    monkeypatch.setattr(_build, "_merge", merge)
    monkeypatch.setattr(_build, "_group_union", group_union)
    monkeypatch.setattr(_build, "_group_order", group_order)
    for name, array in Overview.build_arrays(boxes, kinds):
        if name.split(".")[0].lstrip("-").isdigit() and not name.endswith(".parent"):
            held.append((name, weakref.ref(array)))
        del array
    assert len({name.split(".")[0] for name, _ in held}) > 3 and len(merges) > 3


def test_a_bands_elements_columns_are_made_after_its_sort_and_let_go_before_its_tree(monkeypatch):
    """A band's elements (the band below's aggregates and the items that join) have their
    areas, counts and z made only once their cells are sorted (the sort's keys and order are
    not held beside them: 16 bytes an element less through the band's peak), and
    those, and their boxes, are held by nothing once reduced, when the band's tree is built
    over its aggregates: the build never holds both."""
    import weakref

    from spatial.overview import _build

    boxes, kinds = scenes.uniform(n=4000, seed=5)
    elements: list[weakref.ref] = []
    made, bulk_load = _build._elements, QuadTree.bulk_load_owned.__func__
    cell_order = _build._cell_order
    built, sorts = [], []
    making: list[bool] = []  # this band's columns made yet

    def elements_of(*args):
        boxes, columns = made(*args)
        making.append(False)
        elements[:] = [weakref.ref(boxes.below)]
        area, count_and_z = columns.area, columns.count_and_z

        def seen(*out):
            making[-1] = True
            elements.extend(weakref.ref(c) for c in out)
            return out

        def counted():  # the band below's counts and z, and the items' z (the caller's)
            counts, z, item_z = count_and_z()
            return (*seen(counts, z), item_z)

        columns.area = lambda out: seen(area(out))[0]
        columns.count_and_z = counted
        return [boxes, columns]

    def sort(*args):
        assert not making[-1], "a band's elements' columns made before their cells are sorted"
        sorts.append(len(args[0]))
        return cell_order(*args)

    def tree_of(cls, *args, **options):
        alive = sum(ref() is not None for ref in elements)
        assert not alive, f"{alive} of a band's {len(elements)} element columns held while its tree is built"
        built.append(len(args[0]))
        return bulk_load(cls, *args, **options)

    monkeypatch.setattr(_build, "_elements", elements_of)
    monkeypatch.setattr(_build, "_cell_order", sort)
    monkeypatch.setattr(QuadTree, "bulk_load_owned", classmethod(tree_of))
    for _name, array in Overview.build_arrays(boxes, kinds):
        del array  # written, and let go (a band's counts and z are the band above's elements')
    assert len(built) > 3 and len(sorts) >= len(built)


def test_after_edits_each_aggregate_counts_and_covers_its_members_and_tops_them():
    """An aggregate's count and cover (its members' summed area over its box's) stay those of
    the members it holds, and its z at least their highest, through random inserts, moves and
    removals, at every band: what the page draws by."""
    rng = np.random.default_rng(5)
    n = 600
    boxes = _random_boxes(rng, n)
    z = rng.integers(0, 10, n)
    overview = Overview.build(boxes, np.zeros(n, np.int64), z)
    live = {i: (tuple(boxes[i]), int(z[i])) for i in range(n)}
    for _ in range(400):
        item = int(rng.integers(0, n + 100))
        if item in live and rng.random() < 0.4:  # a removal
            overview.remove(item, live.pop(item)[0])
            continue
        if item in live:  # a move, with a new z
            overview.remove(item, live[item][0])
        box, top = tuple(_random_boxes(rng, 1)[0]), int(rng.integers(0, 20))
        overview.insert(item, box, 0, top)
        live[item] = (box, top)
    for band in range(overview.lo, overview.hi + 1):
        members: dict[int, list[int]] = {}
        for item in live:
            index = overview.aggregate_of(item, band)
            if index is not None:
                members.setdefault(index, []).append(item)
        for index, held in members.items():
            agg = overview.get(band, index)
            area = sum((live[i][0][2] - live[i][0][0]) * (live[i][0][3] - live[i][0][1]) for i in held)
            w, h = agg.box[2] - agg.box[0], agg.box[3] - agg.box[1]
            assert agg.count == len(held), (band, index)
            assert agg.cover == pytest.approx(
                min(1.0, area / (w * h)) if w * h > 0 else 1.0, rel=1e-9, abs=1e-12
            )
            # Raised by each member that joins; a removal leaves it (a maximum is not undone
            # without its members), so it is at least the highest member's.
            assert agg.z >= max(live[i][1] for i in held), (band, index)


def _moved_again_and_again(seed: int) -> tuple[Overview, dict[int, tuple[float, ...]]]:
    """An overview of 200 items of which 10 moved 60 times in all, with ``FOLD_AFTER`` lowered
    (conftest) so its edits lie in runs of folded arrays, and ``{item: box}`` as they are now.
    Some item's older run and newer run hold different homes for it: a read that let the older
    win would be seen."""
    rng = np.random.default_rng(seed)
    boxes = _random_boxes(rng, 200)
    overview = Overview.build(boxes, np.zeros(len(boxes), np.int64))
    live = {i: tuple(boxes[i].tolist()) for i in range(len(boxes))}
    for _ in range(60):
        item = int(rng.integers(0, 10))
        overview.remove(item, live[item])
        live[item] = tuple(_random_boxes(rng, 1)[0].tolist())
        overview.insert(item, live[item])
    homes_in: dict[int, set[tuple[int, int]]] = {}
    for run in overview._folded:
        for item, level, home in zip(run.items.tolist(), run.level.tolist(), run.home.tolist(), strict=True):
            homes_in.setdefault(item, set()).add((level, home))
    assert len(overview._folded) > 1 and any(len(h) > 1 for h in homes_in.values()), "no item in two runs"
    return overview, live


def _live(overview: Overview, band: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(indices, boxes, counts)`` of ``band``'s aggregates that hold members now."""
    indices = overview.query(band, EVERYTHING)
    boxes, count = overview.rows(band, indices)[:2]
    return indices, boxes, count


def _holds(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    return (outer[:, :2] <= inner[:, :2]).all(axis=1) & (inner[:, 2:] <= outer[:, 2:]).all(axis=1)


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_after_items_move_again_and_again_each_ones_aggregate_at_every_band_is_the_one_holding_it(seed):
    """``homes`` (what the masks draw moved items by) answers each item's aggregate as the
    newest edit left it, at every band: brute force over the items as they are now says it
    is live and contains the item's box, its count is the items that name it, and an item of
    the band's size or more has none."""
    overview, live = _moved_again_and_again(seed)
    items = np.array(sorted(live), np.int64)
    boxes = np.array([live[i] for i in items.tolist()])
    for band in range(overview.lo, overview.hi + 1):
        homes = overview.homes(items, band)
        small = _sizes(boxes) < overview.threshold(band)
        assert (homes[~small] == -1).all(), f"band {band}: an item drawn itself has an aggregate"
        indices, agg_boxes, count = _live(overview, band)
        slot = np.searchsorted(np.sort(indices), homes[small])
        slot = np.minimum(slot, len(indices) - 1)
        order = np.argsort(indices)
        assert (indices[order][slot] == homes[small]).all(), f"band {band}: an item's aggregate is not live"
        assert _holds(agg_boxes[order][slot], boxes[small]).all(), (
            f"band {band}: item {items[small][~_holds(agg_boxes[order][slot], boxes[small])][:1]} "
            "is outside the aggregate homes() gives it"
        )
        assert (np.bincount(slot, minlength=len(indices)) == count[order]).all(), (
            f"band {band}: an aggregate's count is not the items homes() puts in it"
        )


@pytest.mark.parametrize("seed", [11, 12])
def test_after_items_move_again_and_again_each_aggregates_parent_at_every_band_above_holds_it(seed):
    """``ancestors`` (what the masks draw finer aggregates by) takes each live aggregate to
    one of a band above that contains its box, and that one's count is brute force's: the
    counts of the aggregates below it plus the items between the two bands' sizes in it."""
    overview, live = _moved_again_and_again(seed)
    # An aggregate's parent is set once, by the insert that makes it: runs never disagree on
    # it, so which run a read of parents lets win does not matter (its counts, they do).
    parents: dict[tuple[int, int], set[int]] = {}
    for run in overview._folded:
        for band, rows in run.rows.items():
            for index, parent in zip(rows.indices.tolist(), rows.parent.tolist(), strict=True):
                parents.setdefault((band, index), set()).add(parent)
    assert all(len(p) == 1 for p in parents.values()), "two runs hold different parents for an aggregate"
    items = np.array(sorted(live), np.int64)
    sizes = _sizes(np.array([live[i] for i in items.tolist()]))
    for level in range(overview.lo, overview.hi):
        below, below_boxes, below_count = _live(overview, level)
        for band in range(level + 1, overview.hi + 1):
            up = overview.ancestors(level, below, band)
            indices, agg_boxes, count = _live(overview, band)
            order = np.argsort(indices)
            slot = np.minimum(np.searchsorted(indices[order], up), max(len(indices) - 1, 0))
            assert (indices[order][slot] == up).all(), f"band {level} -> {band}: a parent is not live"
            assert _holds(agg_boxes[order][slot], below_boxes).all(), (
                f"band {level} -> {band}: an aggregate lies outside its parent"
            )
            between = (sizes >= overview.threshold(level)) & (sizes < overview.threshold(band))
            mine = np.searchsorted(indices[order], overview.homes(items[between], band))
            held = np.bincount(slot, below_count, len(indices)) + np.bincount(mine, minlength=len(indices))
            assert (held == count[order]).all(), f"band {level} -> {band}: counts are not their members'"


def _random_boxes(rng, n: int) -> np.ndarray:
    """``n`` boxes of sizes 1 to 400 over a 10,000-unit square."""
    x, y = rng.uniform(0, 10_000, n), rng.uniform(0, 10_000, n)
    w, h = np.exp(rng.uniform(0, 6, n)), np.exp(rng.uniform(0, 6, n))
    return np.column_stack([x, y, x + w, y + h])


@given(st.lists(st.integers(1, 40), max_size=30), st.integers(1, 50), st.integers(0, 2**32 - 1))
def test_each_aggregates_areas_summed_a_step_at_a_time_are_reduceats(sizes, step, seed):
    """The areas' sums, made a step of elements at a time (a group read to its end wherever it
    begins), are numpy's ``reduceat`` of them all, bit for bit (its pairwise sum rounds as a
    plain one would not), groups across steps and longer than one included."""
    from spatial.overview._build import _sums

    rng = np.random.default_rng(seed)
    starts = np.concatenate(([0], np.cumsum(sizes))).astype(np.int32 if seed % 2 else np.int64)  # either
    values = rng.random(int(starts[-1])) * 10.0 ** rng.integers(-5, 5, int(starts[-1]))
    order = rng.permutation(len(values)).astype(np.int32)
    whole = np.add.reduceat(values[order], starts[:-1]) if sizes else np.empty(0)
    assert _sums(values[order], starts, np.empty(len(starts) - 1), step).tobytes() == whole.tobytes()


def test_an_overview_built_into_a_homes_array_given_is_the_one_built_without():
    """``build_arrays`` makes the items' homes in an array given (an import's, in a file),
    whatever it held, and refuses one of another type or length, saying which."""
    boxes, kinds = scenes.uniform(n=3000, seed=4)
    want = dict(Overview.build_arrays(boxes, kinds))
    homes = np.full(len(boxes), 7, np.int32)
    got = dict(Overview.build_arrays(boxes, kinds, homes=homes))
    assert got["homes"] is homes and got.keys() == want.keys()
    assert all(got[k].tobytes() == want[k].tobytes() for k in want)
    with pytest.raises(ValueError, match="homes must be int32, one an item"):
        dict(Overview.build_arrays(boxes, kinds, homes=np.zeros(len(boxes), np.int64)))
