"""``coords="float32"``: half the memory for built boxes, rounded outward, so a query never
misses an item brute force in float64 finds; what it adds are false hits, counted elsewhere."""

import numpy as np
import oracle
import pytest
from hypothesis import given
from hypothesis import strategies as st

from spatial import QuadTree

MAGNITUDES = [0.0, 1e2, 1e6, 2.0**24, 1.6e8, 1e12, 1e15, -1e15]


@given(
    offset=st.sampled_from(MAGNITUDES),
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 400),
)
def test_float32_never_misses_and_its_diffs_match_its_queries(offset, seed, n):
    rng = np.random.default_rng(seed)
    lo = offset + rng.uniform(0, 1000, (n, 2)) * rng.choice([1e-6, 1.0, 100.0])
    boxes = np.hstack([lo, lo + rng.uniform(0, 50, (n, 2))])
    tree = QuadTree.bulk_load(boxes, coords="float32", leaf_size=4)
    tree._check()
    assert tree._boxes.dtype == np.float32
    for _ in range(10):
        x, y = boxes[rng.integers(n), :2]
        old = (x - 30.0, y - 20.0, x + 40.0, y + 25.0)
        new = (old[0] + 7.5, old[1] - 3.0, old[2] + 7.5, old[3] - 3.0)
        for rect in (old, new):
            assert oracle.query(boxes, np.arange(n), rect) <= set(tree.query(rect).tolist())
            lod = oracle.query(boxes, np.arange(n), rect, min_size=20.0)  # rounded sizes are never smaller
            assert lod <= set(tree.query(rect, min_size=20.0).tolist())
        entered, left = tree.diff(old, new)
        a, b = set(tree.query(old).tolist()), set(tree.query(new).tolist())
        assert (set(entered.tolist()), set(left.tolist())) == (b - a, a - b)


def test_an_item_touching_the_viewport_at_2_24_plus_1_is_found():
    edge = 2.0**24 + 1  # not a float32: rounds to 2^24 or 2^24 + 2
    boxes = np.array([[edge - 10, 0.0, edge, 1.0], [edge + 5, 0.0, edge + 6, 1.0]])
    tree = QuadTree.bulk_load(boxes, coords="float32")
    assert 0 in tree.query((edge, 0.0, edge + 1, 1.0)).tolist()


def test_float32_edits_and_compaction_keep_every_item():
    rng = np.random.default_rng(3)
    boxes = np.hstack([rng.uniform(1e8, 1e8 + 1e4, (500, 2))] * 2) + np.array([0, 0, 3.3, 3.3])
    tree = QuadTree.bulk_load(boxes, coords="float32")
    for i in range(0, 500, 2):
        tree.update(i, boxes[i] + 1.0)
        boxes[i] += 1.0
    tree.compact()
    tree._check()
    rect = (1e8, 1e8, 1e8 + 1e4, 1e8 + 1e4)
    assert oracle.query(boxes, np.arange(500), rect) <= set(tree.query(rect).tolist())


def test_coordinates_beyond_float32_are_refused_with_the_fix():
    with pytest.raises(ValueError, match=r"box 1 is beyond float32's range .* use coords='float64'"):
        QuadTree.bulk_load([[0, 0, 1, 1], [0, 0, 1e39, 1]], coords="float32")
    with pytest.raises(ValueError, match="coords must be"):
        QuadTree(coords="float16")
