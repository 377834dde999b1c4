"""Exact answers where indexes usually break: huge and tiny coordinates, edges, duplicates."""

import numpy as np
import oracle
import pytest

from spatial import QuadTree

MAGNITUDES = [1e-9, 1e-3, 1.0, 1e6, 2.0**24 + 1, 1.6e8, 1e12, 1e15]


def check(boxes: np.ndarray, rects, **options) -> None:
    ids = np.arange(len(boxes), dtype=np.int64)
    tree = QuadTree.bulk_load(boxes, **options)
    tree._check()
    for rect in rects:
        assert set(tree.query(rect).tolist()) == oracle.query(boxes, ids, rect), rect


@pytest.mark.parametrize("magnitude", MAGNITUDES)
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_grid_of_boxes_far_from_the_origin_touching_queries_exactly(magnitude, sign):
    # Unit boxes on a grid at the spacing of the coordinates: adjacent boxes share edges.
    origin = sign * magnitude
    unit = max(float(np.spacing(magnitude)) * 4, magnitude * 1e-6)
    grid = np.arange(40) * unit
    x, y = np.meshgrid(origin + grid, origin + grid)
    boxes = np.column_stack([x.ravel(), y.ravel(), x.ravel() + unit, y.ravel() + unit])
    edges = origin + grid[[0, 3, 17, 39]]
    rects = [(a, b, a, b) for a in edges for b in edges]  # a point on four box corners
    rects += [(edges[1], edges[0], edges[2], edges[3]), (origin - unit, origin - unit, origin, origin)]
    rects += [
        (np.nextafter(origin + grid[5], np.inf), origin, np.nextafter(origin + grid[6], -np.inf), origin)
    ]
    check(boxes, rects)


def test_items_exactly_on_every_split_line_are_found():
    # Boxes on the lines a power-of-two subdivision of [0, 1024] would cut along.
    lines = np.arange(0, 1025, 16, dtype=np.float64)
    boxes = np.array([(a, b, a, b) for a in lines for b in lines] + [(a, 0, a, 1024) for a in lines])
    check(boxes, [(a, 0, a, 1024) for a in lines] + [(0, a, 1024, a) for a in lines], leaf_size=4)


def test_empty_tree_answers_empty():
    tree = QuadTree.bulk_load(np.empty((0, 4)))
    assert len(tree) == 0 and tree.bounds is None
    assert tree.query((0, 0, 1, 1)).tolist() == []
    assert [a.tolist() for a in tree.diff((0, 0, 1, 1), (1, 1, 2, 2))] == [[], []]
    tree.insert(3, (0, 0, 0, 0))
    assert tree.query((0, 0, 0, 0)).tolist() == [3]
    tree._check()


def test_many_identical_points_do_not_recurse_or_slow_the_rest():
    boxes = np.concatenate([np.full((100_000, 4), 7.0), [[0, 0, 1, 1], [100, 100, 101, 101]]])
    tree = QuadTree.bulk_load(boxes)
    tree._check()
    assert tree.depth <= 3
    assert len(tree.query((7, 7, 7, 7))) == 100_000
    assert tree.query((50, 50, 200, 200)).tolist() == [100_001]
    assert len(tree.query((7, 7, 7, 7), exact=False)) >= 100_000


def test_zero_size_boxes_and_a_box_covering_everything():
    rng = np.random.default_rng(3)
    points = rng.uniform(-1e6, 1e6, (5_000, 2))
    boxes = np.concatenate([np.column_stack([points, points]), [[-1e300, -1e300, 1e300, 1e300]]])
    rects = [(p[0], p[1], p[0], p[1]) for p in points[:50]] + [
        (-1e308, -1e308, 1e308, 1e308),
        (2e6, 2e6, 3e6, 3e6),
    ]
    check(boxes, rects)


def test_boxes_far_outside_the_first_load_are_found_after_inserts():
    tree = QuadTree.bulk_load(np.array([[0, 0, 1, 1], [2, 2, 3, 3]]))
    tree.insert(10, (1e15, -1e15, 1e15 + 1, -1e15 + 1))
    tree.insert(11, (-1e-9, -1e-9, 0, 0))
    tree.compact()
    tree._check()
    assert tree.query((1e15, -1e15, 1e15, -1e15)).tolist() == [10]
    assert sorted(tree.query((-1e-9, -1e-9, 0, 0)).tolist()) == [0, 11]


def test_ten_items_spread_over_a_trillion_units_cost_kilobytes():
    boxes = np.array([[i * 1e11, -i * 1e11, i * 1e11 + 1, -i * 1e11 + 1] for i in range(10)])
    tree = QuadTree.bulk_load(boxes, leaf_size=1)
    assert tree.nbytes < 4096
    check(boxes, [tuple(b) for b in boxes])


def test_viewports_larger_than_the_world_or_outside_it():
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 100, (2_000, 2))
    boxes = np.column_stack([xy, xy + 1])
    check(
        boxes, [(-1e15, -1e15, 1e15, 1e15), (200, 200, 300, 300), (-5, -5, -1e-9, -1e-9), (101, 0, 1e9, 1e9)]
    )


def test_memory_grows_with_items_not_with_extent():
    rng = np.random.default_rng(5)
    unit = rng.uniform(0, 1, (20_000, 2))
    small = np.column_stack([unit, unit + 1e-3])
    huge = small * 1e12
    a, b = QuadTree.bulk_load(small), QuadTree.bulk_load(huge)
    assert a.nbytes == pytest.approx(b.nbytes, rel=0.2)
    assert a.nbytes / 20_000 <= 64


@pytest.mark.parametrize("max_depth", [0, 1, 3])
def test_a_depth_cap_bounds_the_tree_and_keeps_answers_exact(max_depth):
    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 1000, (3_000, 2))
    boxes = np.column_stack([xy, xy + rng.uniform(0, 20, (3_000, 2))])
    tree = QuadTree.bulk_load(boxes, leaf_size=2, max_depth=max_depth)
    tree._check()
    assert tree.depth <= max_depth + 1
    check(
        boxes, [(100, 100, 400, 300), (0, 0, 0, 0), (999, 999, 2000, 2000)], leaf_size=2, max_depth=max_depth
    )


def test_a_world_far_narrower_than_a_float_spacing_of_its_coordinates_is_one_cell():
    # Half the side over two spacings underflows to 0: log2 of it is no error, one cell.
    boxes = np.array(
        [
            [0.0, 2.21582787e276, 2.74531156e-63, 2.21582787e276],
            [1e-70, 2.21582787e276, 2e-63, 2.21582787e276],
        ]
        * 50
    )  # past a leaf
    ids = np.arange(len(boxes))
    tree = QuadTree.bulk_load(boxes, ids=ids)
    for rect in ((0, 0, 1, 3e276), (0, 0, 1e-65, 2.2e276), (1e-60, 0, 1, 3e276)):
        assert set(tree.query(rect).tolist()) == oracle.query(boxes, ids, rect)
