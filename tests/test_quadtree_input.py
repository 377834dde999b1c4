"""Bad input found by porting other indexes' suites: the first bad row, ids, and min_size shapes."""

import math
import re

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from spatial import QuadTree
from spatial.rect import as_rect, first_bad_box

NAN, INF = math.nan, math.inf
INT64_MAX, INT64_MIN = 2**63 - 1, -(2**63)


def ten_boxes() -> QuadTree:
    return QuadTree.bulk_load([[i, i, i + 1, i + 1] for i in range(10)])


# -- 1. the first bad row, whatever makes it bad --------------------------------------------


@pytest.mark.parametrize(
    ("boxes", "message"),
    [
        ([[0, 0, 1, 1], [0, 5, 1, 4], [5, 0, 4, 1]], r"^box 1 has y0=5.0 > y1=4.0; swap them$"),
        ([[0, 0, 1, 1], [5, 0, 4, 1], [0, NAN, 1, 1]], r"^box 1 has x0=5.0 > x1=4.0; swap them$"),
        ([[0, 3, 1, 2], [INF, 0, INF, 1]], r"^box 0 has y0=3.0 > y1=2.0; swap them$"),
        ([[5, 5, 4, NAN]], r"^box 0 has y1=nan; coordinates must be finite$"),  # in a row: not finite first
        ([[5, 5, 4, 4]], r"^box 0 has x0=5.0 > x1=4.0; swap them$"),  # then x before y
    ],
)
def test_bulk_load_names_the_first_bad_row_whatever_the_reason(boxes, message):
    with pytest.raises(ValueError, match=message):
        QuadTree.bulk_load(boxes)


coordinate = st.sampled_from([0.0, 1.0, 2.0, -1.0] * 6 + [NAN, INF, -INF])  # mostly finite rows


@given(st.lists(st.tuples(coordinate, coordinate, coordinate, coordinate), min_size=1, max_size=8))
def test_first_bad_box_agrees_with_checking_each_row_alone(rows):
    expected = None
    for row, box in enumerate(rows):
        try:
            as_rect(box, "box")
        except ValueError as error:
            expected = row, str(error).removeprefix("box has ")
            break
    assert first_bad_box(np.array(rows, dtype=np.float64)) == expected


# -- 2. ids are integers: no float is truncated into another item's id ----------------------


@pytest.mark.parametrize("bad_id", [8.5, 8.0, np.float64(8.0), True, "8", None])
@pytest.mark.parametrize("edit", ["insert", "remove", "update", "get"])
def test_edits_refuse_ids_that_are_not_integers_and_name_them(edit, bad_id):
    tree = ten_boxes()
    args = (bad_id, (50, 50, 51, 51)) if edit in ("insert", "update") else (bad_id,)
    with pytest.raises(ValueError, match=rf"id {re.escape(repr(bad_id))} is not an integer"):
        getattr(tree, edit)(*args)
    assert len(tree) == 10 and tree.get(8) == (8.0, 8.0, 9.0, 9.0) and tree.get(1) == (1.0, 1.0, 2.0, 2.0)
    tree._check()


@pytest.mark.parametrize("bad_id", [8.5, 8.0, np.float64(8.0), True, "8", None, [8], 2**63, -(2**63) - 1])
def test_contains_is_false_for_anything_but_an_int64_integer(bad_id):
    assert bad_id not in ten_boxes()


def test_numpy_integers_are_ids_like_python_ints():
    tree = ten_boxes()
    assert np.int64(8) in tree and np.uint8(8) in tree
    tree.update(np.int32(8), (0, 0, 1, 1))
    assert tree.get(np.uint64(8)) == (0.0, 0.0, 1.0, 1.0)
    tree.insert(np.int16(20), (2, 2, 3, 3))
    tree.remove(np.int64(20))
    assert 20 not in tree and len(tree) == 10
    tree._check()


# -- 3. ids beyond int64 are refused, not wrapped -------------------------------------------


@pytest.mark.parametrize(
    ("ids", "bad"),
    [
        ([2**63], 2**63),
        ([0, 2**64], 2**64),
        ([2**63, -1], 2**63),  # numpy makes this list float64
        ([0, -(2**63) - 1], -(2**63) - 1),
        (np.array([1, 2**63], dtype=np.uint64), 2**63),
    ],
)
def test_bulk_load_refuses_ids_beyond_int64_naming_them(ids, bad):
    boxes = [[0, 0, 1, 1]] * len(ids)
    with pytest.raises(ValueError, match=rf"id {bad} is outside int64's range \[-2\*\*63, 2\*\*63 - 1\]"):
        QuadTree.bulk_load(boxes, ids=ids)


@pytest.mark.parametrize("bad", [2**63, -(2**63) - 1, 10**30])
def test_insert_refuses_ids_beyond_int64_with_value_error(bad):
    tree = ten_boxes()
    with pytest.raises(ValueError, match=rf"id {bad} is outside int64's range"):
        tree.insert(bad, (0, 0, 1, 1))
    assert len(tree) == 10


def test_ids_at_both_ends_of_int64_are_kept_exactly():
    tree = QuadTree.bulk_load([[0, 0, 1, 1], [2, 2, 3, 3]], ids=[INT64_MAX, INT64_MIN])
    assert sorted(tree.query((0, 0, 3, 3)).tolist()) == [INT64_MIN, INT64_MAX]
    tree.remove(INT64_MAX)
    tree.insert(INT64_MAX, (5, 5, 6, 6))
    assert tree.get(INT64_MAX) == (5.0, 5.0, 6.0, 6.0) and INT64_MIN in tree
    unsigned = QuadTree.bulk_load([[0, 0, 1, 1]], ids=np.array([INT64_MAX], np.uint64))
    assert unsigned.query((0, 0, 1, 1)).tolist() == [INT64_MAX]


def test_bulk_load_still_refuses_float_and_bool_ids_naming_the_first():
    with pytest.raises(ValueError, match=r"id 2.5 is not an integer"):
        QuadTree.bulk_load([[0, 0, 1, 1]] * 2, ids=[1, 2.5])
    with pytest.raises(ValueError, match=r"id True is not an integer"):
        QuadTree.bulk_load([[0, 0, 1, 1]] * 2, ids=np.array([True, False]))


# -- 4. min_size is one number (or, for diff, an (old, new) pair) ---------------------------


@pytest.mark.parametrize("min_size", [[0, 50], (1, 2), np.array([1.0, 2.0]), "big", None])
def test_query_refuses_a_min_size_that_is_not_one_number_naming_it(min_size):
    with pytest.raises(ValueError, match=rf"min_size must be one number, got {re.escape(repr(min_size))}"):
        ten_boxes().query((0, 0, 5, 5), min_size=min_size)


@pytest.mark.parametrize("min_size", [(1,), (1, 2, 3), (), "big", [[1, 2]]])
def test_diff_refuses_a_min_size_that_is_not_a_number_or_a_pair_naming_it(min_size):
    with pytest.raises(ValueError, match=rf"min_size must be .*got {re.escape(repr(min_size))}"):
        ten_boxes().diff((0, 0, 5, 5), (1, 1, 6, 6), min_size=min_size)


def test_diff_takes_min_size_as_one_number_or_an_old_new_pair():
    tree = ten_boxes()
    as_tuple = tree.diff((0, 0, 5, 5), (1, 1, 6, 6), min_size=(0.0, 2.0))
    as_list = tree.diff((0, 0, 5, 5), (1, 1, 6, 6), min_size=[0.0, 2.0])
    assert (
        [sorted(a.tolist()) for a in as_tuple]
        == [sorted(a.tolist()) for a in as_list]
        == [[], [0, 1, 2, 3, 4, 5]]
    )
    entered, left = tree.diff((0, 0, 5, 5), (1, 1, 6, 6), min_size=np.float64(0.5))
    assert (entered.tolist(), left.tolist()) == ([6], [])
