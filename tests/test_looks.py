"""Kinds and z read from items' JSON by the compiled scan agree with decoding it, tricky
bodies included, and aggregates go out in an item's shape with an id no item can have."""

import msgspec
import numpy as np
import pytest

import app.packed
from app.items import Item
from app.looks import Looks, agg_id, agg_json, parse_agg_id
from app.table import Packed, fnv1a
from spatial.overview import Overview

TRICKY = [
    Item("plain", 0, 0, 1, 1, "text", 3),
    Item('an id spelling ,"kind":"page","z":9', 0, 0, 1, 1, "note", -7),
    Item("escaped", 0, 0, 1, 1, 'te"xt\\n', 2**31 - 1),
    Item("data", 0, 0, 1, 1, "box", 0, {"kind": "page", "z": 5}),
    Item("unicode", 0, 0, 1, 1, "pâge ✓", -(2**31)),
    Item("default", 0, 0, 1, 1),
]


def test_a_column_of_one_value_is_held_once():
    """Each item's kind code and z, for the overview's build: a column whose items all hold
    one value is that value broadcast (4 bytes an item less through the build's peak), the
    others a value an item."""
    same = [msgspec.json.encode(Item(f"i{k}", 0, 0, 1, 1, "text")) for k in range(50)]
    _, kinds, z = Looks.of(Packed.of(same))
    assert kinds.strides == z.strides == (0,) and kinds.tolist() == [0] * 50 and z.tolist() == [0] * 50
    mixed = [*same, msgspec.json.encode(Item("o", 0, 0, 1, 1, "text", 4))]
    _, kinds, z = Looks.of(Packed.of(mixed))
    assert kinds.strides == (0,) and z.strides == (4,) and z.tolist() == [0] * 50 + [4]
    _, kinds, z = Looks.of(Packed.of([]))
    assert len(kinds) == len(z) == 0


@pytest.fixture(params=["one step", "steps of ~2 items"])
def steps(request, monkeypatch):
    """Whole, or a few items a step (a spilled import's bodies are read a step at a time, and
    each step's kinds coded as it comes)."""
    if request.param != "one step":
        monkeypatch.setattr(app.packed, "STEP_BYTES", 160)


def test_the_scan_reads_each_kind_and_z_as_decoding_does(steps):
    bodies = [msgspec.json.encode(item) for item in TRICKY]
    looks, kinds, z = Looks.of(Packed.of(bodies))
    assert [looks.names[k] for k in kinds.tolist()] == [item.kind for item in TRICKY]
    assert z.tolist() == [item.z for item in TRICKY]
    assert looks.of_body(bodies[2]) == (looks.codes['te"xt\\n'], 2**31 - 1)
    more = looks.with_item(msgspec.json.encode(Item("x", 0, 0, 1, 1, "frame")))
    assert more.names[-1] == "frame" and more.codes["frame"] == len(looks.names)


@pytest.mark.parametrize("kinds", [1, 7, 4096, 4097, 9000])
def test_kinds_are_coded_in_hash_order_few_or_many(kinds, steps):
    """Codes and names as a sort of every item's hash gives them, whether the kinds are few
    (found in one pass) or more than the pass keeps (every hash sorted, from the step that
    finds one too many)."""
    rng = np.random.default_rng(kinds)
    items = [Item(f"i{n}", 0, 0, 1, 1, f"k{rng.integers(kinds)}", n % 5) for n in range(3 * kinds)]
    looks, codes, z = Looks.of(Packed.of([msgspec.json.encode(item) for item in items]))
    assert [looks.names[k] for k in codes.tolist()] == [item.kind for item in items]
    assert z.tolist() == [item.z for item in items]
    hashes = fnv1a(*_packed([item.kind.encode() for item in items]))
    assert list(looks.names) == [items[i].kind for i in np.unique(hashes, return_index=True)[1]]


def _packed(parts: list[bytes]) -> tuple[np.ndarray, np.ndarray]:
    packed = Packed.of(parts)
    return packed.array, packed.offsets


@pytest.mark.parametrize("key", [(6, 1207), (-3, 0), (1023, 12)])
def test_aggregate_ids_round_trip_and_are_never_item_ids(key):
    assert parse_agg_id(agg_id(key)) == key and agg_id(key).startswith("~")
    assert parse_agg_id("w17") is None


def test_an_aggregate_goes_out_in_an_items_shape():
    view = Overview.build(np.array([[0, 0, 4, 2], [5, 0, 9, 2]]), kinds=[1, 1], z=[2, 3])
    (body,) = agg_json(view, ("page", "text"), 4, view.query(4, (0, 0, 9, 9)))
    entry = msgspec.json.decode(body)
    assert entry == {
        "id": "~4.0",
        "x0": 0.0,
        "y0": 0.0,
        "x1": 9.0,
        "y1": 2.0,
        "kind": "text",
        "z": 3,
        "agg": {"count": 2, "cover": pytest.approx(16 / 18, abs=1e-3)},
    }
