"""The API at the extremes: what it accepts round-trips to the last bit and is found exactly;
what it refuses gets a 422 that says why. The range is every finite double."""

import numpy as np
import oracle
import orjson
import pytest
from service import NDJSON

MAGNITUDES = [1e-9, 1.0, 2.0**24 + 1, 1.6e8, 1e12, 1e15]
HUGE = float(np.finfo(np.float64).max)


def _doubles(rng, magnitude, n):
    """Doubles near ``magnitude`` with all 17 significant digits in use."""
    return magnitude * (1 + rng.random(n)) * rng.choice([-1.0, 1.0], n)


def test_coordinates_round_trip_exactly_and_touching_edges_are_found(document):
    c, doc, _ = document
    rng = np.random.default_rng(17)
    rows = []
    for magnitude in MAGNITUDES:
        x0, y0 = _doubles(rng, magnitude, 20), _doubles(rng, magnitude, 20)
        w, h = magnitude * rng.random(20) * 1e-3, magnitude * rng.random(20) * 1e-3
        rows.append(np.column_stack([x0, y0, x0 + w, y0 + h]))
    boxes = np.concatenate(rows)
    lines = [
        orjson.dumps({"id": f"x{i}", "x0": b[0], "y0": b[1], "x1": b[2], "y1": b[3]})
        for i, b in enumerate(boxes.tolist())
    ]
    lines.append(orjson.dumps({"id": "everything", "x0": -HUGE, "y0": -HUGE, "x1": HUGE, "y1": HUGE}))
    assert c.post(f"/documents/{doc}/items", content=b"\n".join(lines), headers=NDJSON).status_code == 200
    for i in rng.choice(len(boxes), 30, replace=False).tolist():
        item = c.get(f"/documents/{doc}/items/x{i}").json()
        assert [item[k] for k in ("x0", "y0", "x1", "y1")] == boxes[i].tolist()  # every bit
        x0, y0, x1, y1 = boxes[i].tolist()
        for rect in ((x1, y1, x1, y1), (x0 - abs(x0) * 1e-3, y0, x0, y0)):  # touching a corner / an edge
            params = {**dict(zip(("x0", "y0", "x1", "y1"), map(repr, rect), strict=True)), "limit": 100_000}
            got = {it["id"] for it in c.get(f"/documents/{doc}/viewport", params=params).json()["items"]}
            want = {f"x{k}" for k in np.flatnonzero(oracle.hits(boxes, rect))} | {"everything"}
            assert f"x{i}" in got and {g for g in got if g.startswith("x") or g == "everything"} == want
    everything = c.get(f"/documents/{doc}/items/everything").json()
    assert (everything["x0"], everything["x1"]) == (-HUGE, HUGE)


@pytest.mark.parametrize(
    ("line", "why"),
    [
        (b'{"id": "n", "x0": NaN, "y0": 0, "x1": 1, "y1": 1}', "JSON is malformed"),
        (b'{"id": "n", "x0": -Infinity, "y0": 0, "x1": 1, "y1": 1}', "JSON is malformed"),
        (b'{"id": "n", "x0": 0, "y0": 0, "x1": 1e309, "y1": 1}', "Number out of range - at `$.x1`"),
        (
            b'{"id": "n", "x0": 2e15, "y0": 0, "x1": 1e15, "y1": 1}',
            "x0=2000000000000000.0 > x1=1000000000000000.0; swap them",
        ),
        (b'{"id": "n", "x0": 0, "y0": 1e-9, "x1": 1, "y1": 1e-10}', "y0=1e-09 > y1=1e-10; swap them"),
    ],
)
def test_what_is_refused_says_why(document, line, why):
    c, doc, _boxes = document
    answer = c.post(f"/documents/{doc}/items", content=line + b"\n", headers=NDJSON)
    assert answer.status_code == 422 and why in answer.json()["detail"], answer.text
    put = c.put(
        f"/documents/{doc}/items/n", content=line, headers={"content-type": "application/json"}
    )  # a single edit may not name the field
    assert put.status_code == 422 and why.split(" - at")[0] in put.json()["detail"], put.text
    assert c.get(f"/documents/{doc}").json()["version"] == 1


@pytest.mark.parametrize(
    ("params", "why"),
    [
        ({"x0": "nan", "y0": 0, "x1": 1, "y1": 1}, "finite"),
        ({"x0": 0, "y0": "-inf", "x1": 1, "y1": 1}, "finite"),
        ({"x0": 0, "y0": 0, "x1": "1e309", "y1": 1}, "finite"),
        ({"x0": 5, "y0": 0, "x1": 4, "y1": 1}, "x0=5.0 > x1=4.0"),
    ],
)
def test_bad_viewports_say_why(document, params, why):
    c, doc, _ = document
    answer = c.get(f"/documents/{doc}/viewport", params=params)
    assert answer.status_code == 422 and why in str(answer.json()["detail"]), answer.text
