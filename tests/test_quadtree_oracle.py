"""Every answer of the tree, on several kinds of scene, equals brute force."""

import functools
import itertools
import tempfile
from pathlib import Path
from unittest import mock

import numpy as np
import oracle
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.table import scratch_array
from spatial import QuadTree, _kernels, scenes, sorting, touches
from spatial.paging import mapping

pytestmark = pytest.mark.usefixtures("scratch_in_files")  # small inputs, mapped paths


def random_scene(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-5_000, 5_000, (n, 2))
    wh = rng.lognormal(2.0, 1.2, (n, 2))
    return np.column_stack([xy, xy + wh])


SCENES = {
    "random": lambda: random_scene(20_000, 1),
    "clustered": lambda: scenes.whiteboard(20_000, seed=2, clusters=12)[0],
    "document": lambda: scenes.long_document(pages=40, seed=3)[0],
    "uniform": lambda: scenes.uniform(20_000, seed=4)[0],
    # Nested page > block > line > word boxes, in one column and side by side in a grid.
    "pdf column": lambda: scenes.pdf_pages(pages=40, columns=1, seed=13)[0],
    "pdf grid": lambda: scenes.pdf_pages(pages=50, columns=25, seed=14)[0],
    "sparse": lambda: scenes.sparse(20_000, seed=15)[0],
}


@pytest.fixture(scope="module", params=sorted(SCENES))
def scene(request):
    boxes = SCENES[request.param]()
    ids = np.random.default_rng(5).permutation(boxes.shape[0]).astype(np.int64) * 7 - 1000
    return boxes, ids


def viewports(boxes: np.ndarray, count: int, seed: int) -> np.ndarray:
    """Panning-path viewports plus random rectangles of every shape, some missing everything."""
    rng = np.random.default_rng(seed)
    path = scenes.panning_path(boxes, count, seed=seed)
    lo, hi = boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)
    corner = rng.uniform(lo - 100, hi + 100, (count, 2))
    size = rng.exponential((hi - lo) / 20, (count, 2))
    return np.concatenate([path, np.column_stack([corner, corner + size])])


@pytest.mark.parametrize("options", [{}, {"x_order": False}, {"leaf_size": 1}, {"leaf_size": 200}])
def test_query_equals_brute_force(scene, options):
    boxes, ids = scene
    tree = QuadTree.bulk_load(boxes, ids, **options)
    tree._check()
    for rect in viewports(boxes, 60, seed=6):
        got = tree.query(rect)
        assert got.dtype == np.int64
        assert len(got) == len(set(got.tolist())), "an id came back twice"
        assert set(got.tolist()) == oracle.query(boxes, ids, rect)


def test_candidates_are_a_superset_of_the_exact_answer(scene):
    boxes, ids = scene
    tree = QuadTree.bulk_load(boxes, ids)
    row = {item_id: k for k, item_id in enumerate(ids.tolist())}
    for rect in viewports(boxes, 60, seed=7):
        candidates = tree.query(rect, exact=False)
        assert len(candidates) == len(set(candidates.tolist()))
        assert oracle.query(boxes, ids, rect) <= set(candidates.tolist())
        # and no more than the touched leaves hold: each candidate lies in a leaf touching rect
        leaves = np.array([box for _, box, leaf in tree.cells(rect, limit=1 << 20) if leaf]).reshape(-1, 4)
        own = boxes[[row[c] for c in candidates.tolist()]]
        for part in np.array_split(own, max(1, len(own) // 512)):
            inside = (
                (leaves[None, :, :2] <= part[:, None, :2]) & (part[:, None, 2:] <= leaves[None, :, 2:])
            ).all(axis=2)
            assert inside.any(axis=1).all(), "a candidate from no leaf touching the viewport"


def test_min_size_leaves_out_exactly_the_small_items(scene):
    boxes, ids = scene
    tree = QuadTree.bulk_load(boxes, ids)
    sizes = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
    for rect, quantile in zip(viewports(boxes, 40, seed=8), np.linspace(0, 1, 80), strict=False):
        min_size = float(np.quantile(sizes, quantile))  # includes sizes equal to an item's own
        got = tree.query(rect, min_size=min_size)
        assert set(got.tolist()) == oracle.query(boxes, ids, rect, min_size)


def test_diff_is_exactly_the_difference_of_two_queries(scene):
    boxes, ids = scene
    tree = QuadTree.bulk_load(boxes, ids)
    path = viewports(boxes, 80, seed=9)
    for old, new in itertools.pairwise(path):
        entered, left = tree.diff(old, new)
        before, after = oracle.query(boxes, ids, old), oracle.query(boxes, ids, new)
        assert set(entered.tolist()) == after - before and len(entered) == len(after - before)
        assert set(left.tolist()) == before - after and len(left) == len(before - after)


def test_diff_with_a_different_min_size_per_viewport(scene):
    boxes, ids = scene
    tree = QuadTree.bulk_load(boxes, ids)
    rng = np.random.default_rng(10)
    path = viewports(boxes, 40, seed=10)
    sizes = rng.choice([0.0, 1.0, 5.0, 20.0, 80.0], (len(path), 2))
    for (old, new), (old_size, new_size) in zip(itertools.pairwise(path), sizes, strict=False):
        entered, left = tree.diff(old, new, min_size=(old_size, new_size))
        before = oracle.query(boxes, ids, old, old_size)
        after = oracle.query(boxes, ids, new, new_size)
        assert set(entered.tolist()) == after - before
        assert set(left.tolist()) == before - after


def test_small_pan_steps_diff_exactly(scene):
    boxes, ids = scene
    tree = QuadTree.bulk_load(boxes, ids)
    start = scenes.panning_path(boxes, 1, seed=11)[0]
    for step in ([0, 60, 0, 60], [60, 0, 60, 0], [-13.5, 7.25, -13.5, 7.25], [0, 0, 0, 0]):
        new = start + np.asarray(step)
        entered, left = tree.diff(start, new)
        before, after = oracle.query(boxes, ids, start), oracle.query(boxes, ids, new)
        assert set(entered.tolist()) == after - before
        assert set(left.tolist()) == before - after


def test_zooming_in_place_changes_only_the_level_of_detail(scene):
    boxes, ids = scene
    tree = QuadTree.bulk_load(boxes, ids)
    sizes = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
    small, large = (float(q) for q in np.quantile(sizes, [0.3, 0.7]))
    for rect in scenes.panning_path(boxes, 10, seed=12):
        centre, half = (rect[:2] + rect[2:]) / 2, (rect[2:] - rect[:2]) / 2
        zoomed_out = np.concatenate([centre - 2 * half, centre + 2 * half])
        for old, new, old_size, new_size in (
            (rect, rect, small, large),
            (rect, rect, large, small),
            (rect, zoomed_out, small, large),
            (zoomed_out, rect, large, small),
        ):
            entered, left = tree.diff(old, new, min_size=(old_size, new_size))
            before = oracle.query(boxes, ids, old, old_size)
            after = oracle.query(boxes, ids, new, new_size)
            assert set(entered.tolist()) == after - before
            assert set(left.tolist()) == before - after


def test_a_tree_from_its_arrays_answers_as_the_original_read_only_and_edited():
    boxes, _ = scenes.long_document(pages=20, seed=5)
    arrays = {k: v.copy() for k, v in QuadTree.bulk_load(boxes).to_arrays().items()}
    for array in arrays.values():
        array.setflags(write=False)  # as mapped from a file
    tree = QuadTree.from_arrays(arrays)
    tree._check()
    ids = np.arange(len(boxes))
    for rect in scenes.panning_path(boxes, 40, seed=6):
        assert set(tree.query(rect).tolist()) == oracle.query(boxes, ids, rect)
    edited = tree.copy()
    edited.remove(3)
    edited.insert(10**9, (1.0, 1.0, 2.0, 2.0))
    edited._check()
    with pytest.raises(ValueError, match="compact\\(\\) it first"):
        edited.to_arrays()
    with pytest.raises(ValueError, match="not a tree's arrays"):
        QuadTree.from_arrays({**arrays, "boxes": arrays["boxes"][:-1]})


def test_a_tree_whose_ids_are_its_slots_stores_none_and_answers_as_brute_force():
    """A snapshot file's tree: its items laid out in its order, each id its slot (a fifth
    number in ``shape``), no ids array. Queries, diffs, edits and a rebuild answer with the
    slots, as brute force over the boxes in that order does."""
    boxes, _ = scenes.long_document(pages=12, seed=8)
    built = QuadTree.bulk_load(boxes).to_arrays()
    arrays = {"nodes": built["nodes"], "boxes": built["boxes"], "shape": np.append(built["shape"], 1)}
    for array in arrays.values():
        array.setflags(write=False)
    tree, laid_out = QuadTree.from_arrays(arrays), built["boxes"]
    slots = np.arange(len(laid_out))
    tree._check()
    path = scenes.panning_path(laid_out, 30, seed=9)
    for old, new in itertools.pairwise(path):
        assert set(tree.query(new).tolist()) == oracle.query(laid_out, slots, new)
        assert set(tree.query(new, exact=False).tolist()) >= oracle.query(laid_out, slots, new)
        entered, left = tree.diff(old, new)
        before, after = oracle.query(laid_out, slots, old), oracle.query(laid_out, slots, new)
        assert (set(entered.tolist()), set(left.tolist())) == (after - before, before - after)
    edited = tree.copy()
    for slot in range(0, len(laid_out), 7):
        edited.remove(slot)
    edited.update(1, (0.0, 0.0, 1.0, 1.0))
    moved = laid_out.copy()
    moved[1] = (0.0, 0.0, 1.0, 1.0)
    kept = np.ones(len(laid_out), bool)
    kept[::7] = False
    edited._check()
    for _ in ("tombstones", "rebuilt"):
        for rect in path:
            assert set(edited.query(rect).tolist()) == oracle.query(moved[kept], slots[kept], rect)
        edited.compact()  # then a tree of its own ids
    with pytest.raises(ValueError, match="not a tree's arrays"):
        QuadTree.from_arrays({**arrays, "shape": built["shape"]})  # no ids, and not said to be its slots


def test_each_kind_of_tree_calls_compiled_code_of_its_own_types():
    """A tree looks its compiled kernels up once per build, for its arrays' types (float64,
    float32, read-only as mapped from a file), and answers as brute force through them."""
    from spatial import _kernels, _walk, quadtree

    boxes, _ = scenes.pdf_pages(pages=6, columns=3, seed=16)
    ids = np.arange(len(boxes))
    arrays = {k: v.copy() for k, v in QuadTree.bulk_load(boxes).to_arrays().items()}
    for array in arrays.values():
        array.setflags(write=False)
    trees = [
        QuadTree.bulk_load(boxes),
        QuadTree.bulk_load(boxes, coords="float32"),
        QuadTree.from_arrays(arrays),
    ]
    assert len({id(tree._query) for tree in trees}) == 3, "one compiled query per kind of arrays"
    assert all(tree._query is not _walk.query for tree in trees), "fell back to numba's dispatcher"
    for tree in trees:
        edited = tree.copy()
        edited.remove(5)
        edited.insert(10**6, (10.0, 10.0, 20.0, 20.0))
        for rect in scenes.panning_path(boxes, 20, seed=17):
            want = oracle.query(boxes, ids, rect)
            assert want <= set(tree.query(rect).tolist())  # float32 may add false hits
            if tree.coords == "float64":
                assert set(tree.query(rect).tolist()) == want
                got = set(edited.query(rect).tolist())
                added = {10**6} if touches(rect, (10.0, 10.0, 20.0, 20.0)) else set()
                assert got == (want - {5}) | added
    # where numba's internals are not there, the dispatcher itself
    assert quadtree._compiled(_kernels.bounds, object()) is _kernels.bounds


@settings(max_examples=200, deadline=None)
@given(
    n=st.integers(0, 3000),
    seed=st.integers(0, 2**32 - 1),
    spread=st.sampled_from([1, 3, 2**11, 2**22 + 5, 2**64 - 1]),
    bits=st.integers(0, 64),
    wide=st.booleans(),
)
def test_the_in_place_radix_sort_is_a_stable_argsort_of_the_low_bits(n, seed, spread, bits, wide):
    """The keys' sort with no spare copies (the tree's, the id index's, the overview's cells'):
    the order ``np.argsort(kind="stable")`` gives the keys' low ``bits`` (ties in position
    order), and the keys so ordered. Few distinct keys and many make buckets past the last
    digit and of every size (48 and more are sorted digit by digit, their ties scrambled by
    the swaps until they are put back in order)."""
    dtype = np.uint64 if wide or bits > 32 else np.uint32
    values = np.random.default_rng(seed).integers(0, spread, n, dtype=np.uint64, endpoint=True)
    values = (values & np.uint64(2**bits - 1)).astype(dtype)
    order, sorted_keys = _kernels.radix_sort(values.copy(), np.arange(n, dtype=np.int32), bits)
    want = np.argsort(values, kind="stable")
    assert order.tolist() == want.tolist()
    assert sorted_keys.tolist() == values[want].tolist()


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(0, 400),
    seed=st.integers(0, 2**32 - 1),
    spread=st.sampled_from([1, 3, 2**11, 2**22 + 5, 2**64 - 1]),
    bits=st.integers(0, 64),
    run=st.integers(1, 40),
    step=st.sampled_from([8, 24, 4096]),
)
def test_keys_sorted_in_files_a_run_at_a_time_are_the_sort_in_memory(n, seed, spread, bits, run, step):
    """An import's keys are sorted in files (``sorted_keys`` with a scratch): spread out of
    place by a digit, a step at a time, then each run of whole buckets sorted in memory, a
    bucket past a run spread again by its next digit. Runs of a few keys and steps of one to
    three make every path (a digit alike for all, buckets past a run, keys alike past the
    last digit): the answer is ``np.argsort(kind="stable")``'s, as in memory."""
    values = np.random.default_rng(seed).integers(0, spread, n, dtype=np.uint64, endpoint=True)
    values &= np.uint64(2**bits - 1)
    with tempfile.TemporaryDirectory() as directory:
        scratch = functools.partial(scratch_array, Path(directory))
        keys = scratch(n, np.uint64)
        keys[:] = values
        with mock.patch("spatial.paging.STEP_BYTES", step):
            order, sorted_keys = sorting.sorted_keys(keys, bits, scratch, run_bytes=12 * run)
        assert n < 2 or mapping(order) is not None  # in files, not memory
        want = np.argsort(values, kind="stable")
        assert order.tolist() == want.tolist()
        assert sorted_keys.tolist() == values[want].tolist()
