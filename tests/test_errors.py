"""Bad input is refused at the door with a message that names the value and the fix; a bug
is a 500, never dressed up as a client's error."""

import math

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.config import get_settings
from app.errors import NotFound
from app.main import create_app
from spatial import QuadTree


@pytest.mark.parametrize(
    ("boxes", "message"),
    [
        ([[0, 0, 1, 1], [0, math.nan, 1, 1]], r"box 1 has y0=nan; coordinates must be finite"),
        ([[0, 0, math.inf, 1]], r"box 0 has x1=inf; coordinates must be finite"),
        ([[0, 0, 1, 1], [0, 0, 1, 1], [5, 0, 4, 1]], r"box 2 has x0=5.0 > x1=4.0; swap them"),
        ([[0, 3, 1, 2]], r"box 0 has y0=3.0 > y1=2.0"),
        ([[0, 0, 1]], r"shape \(n, 4\)"),
        ([0, 0, 1, 1], r"shape \(n, 4\)"),
    ],
)
def test_bulk_load_names_the_bad_row(boxes, message):
    with pytest.raises(ValueError, match=message):
        QuadTree.bulk_load(boxes)


def test_bulk_load_refuses_duplicate_and_misshapen_ids():
    with pytest.raises(ValueError, match="id 4 appears more than once"):
        QuadTree.bulk_load([[0, 0, 1, 1]] * 3, ids=[4, 2, 4])
    with pytest.raises(ValueError, match="one per box"):
        QuadTree.bulk_load([[0, 0, 1, 1]] * 3, ids=[1, 2])
    with pytest.raises(ValueError, match="must be integers"):
        QuadTree.bulk_load([[0, 0, 1, 1]], ids=[0.5])


@pytest.mark.parametrize(
    ("rect", "message"),
    [
        ((0, 0, math.nan, 1), "rect has x1=nan"),
        ((-math.inf, 0, 1, 1), "rect has x0=-inf"),
        ((2, 0, 1, 1), "rect has x0=2.0 > x1=1.0"),
        ((0, 2, 1, 1), "rect has y0=2.0 > y1=1.0"),
        ((0, 0, 1), "rect must be four numbers"),
        ("abcd", "rect must be four numbers"),
    ],
)
def test_query_refuses_bad_rects(rect, message):
    tree = QuadTree.bulk_load([[0, 0, 1, 1]])
    with pytest.raises(ValueError, match=message):
        tree.query(rect)


def test_diff_names_which_rect_and_size_is_wrong():
    tree = QuadTree.bulk_load([[0, 0, 1, 1]])
    with pytest.raises(ValueError, match="new_rect has y1=nan"):
        tree.diff((0, 0, 1, 1), (0, 0, 1, math.nan))
    with pytest.raises(ValueError, match="min_size must be finite and >= 0"):
        tree.diff((0, 0, 1, 1), (0, 0, 1, 1), min_size=(0.0, -1.0))
    with pytest.raises(ValueError, match="min_size must be finite and >= 0"):
        tree.query((0, 0, 1, 1), min_size=math.nan)


def test_edits_refuse_bad_boxes_and_leave_the_tree_unchanged():
    tree = QuadTree.bulk_load([[0, 0, 1, 1]])
    with pytest.raises(ValueError, match=r"box has x0=3\.0 > x1=2\.0"):
        tree.insert(1, (3, 0, 2, 1))
    with pytest.raises(ValueError, match="box has y1=inf"):
        tree.update(0, (0, 0, 1, math.inf))
    assert len(tree) == 1 and tree.get(0) == (0.0, 0.0, 1.0, 1.0)
    tree._check()


def test_constructor_refuses_useless_shapes():
    with pytest.raises(ValueError, match="leaf_size must be between 1"):
        QuadTree(leaf_size=0)
    with pytest.raises(ValueError, match="max_depth must be between 0 and 31"):
        QuadTree(max_depth=40)


def test_ids_keep_their_int64_range():
    big = np.array([2**62, -(2**62), 0], dtype=np.int64)
    tree = QuadTree.bulk_load([[0, 0, 1, 1], [2, 2, 3, 3], [4, 4, 5, 5]], ids=big)
    assert sorted(tree.query((0, 0, 5, 5)).tolist()) == sorted(big.tolist())


def test_a_stray_key_error_in_a_route_is_a_500_not_a_404(data_dir):
    app = create_app(get_settings())

    @app.get("/lookup/{kind}")
    async def lookup(kind: str) -> dict:
        if kind == "missing":
            raise NotFound("no such thing")  # a LookupError the service means: 404
        return {}["key"]  # a bug

    with TestClient(app, base_url="http://127.0.0.1", raise_server_exceptions=False) as c:
        missing = c.get("/lookup/missing")
        assert (missing.status_code, missing.json()) == (404, {"detail": "no such thing"})
        bug = c.get("/lookup/bug")
        assert bug.status_code == 500 and "key" not in bug.text, bug.text
