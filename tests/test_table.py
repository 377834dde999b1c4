"""The packed byte strings every answer is joined from, against plain Python's join."""

import io
import mmap
from unittest import mock

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from service import mapped_bytes

import app.folding
import app.packed
import app.table
from app.folding import folded
from app.packed import STEP_BYTES, Packed
from app.table import ItemTable
from spatial import MemoryBudget
from spatial.paging import mapping

pytestmark = pytest.mark.usefixtures("scratch_in_files")  # small inputs, mapped paths

parts_and_picks = st.lists(st.binary(max_size=40), max_size=30).flatmap(
    lambda parts: st.tuples(
        st.just(parts),
        st.lists(st.integers(0, len(parts) - 1), max_size=60) if parts else st.just([]),
        st.sampled_from([b",", b"\n"]),
        st.tuples(st.binary(max_size=8), st.binary(max_size=8)),
    )
)


@given(parts_and_picks)
def test_join_is_pythons_join_of_the_picked_parts_between_the_ends(case):
    parts, picks, sep, (head, tail) = case
    packed = Packed.of(parts)
    joined = head + sep.join(parts[p] for p in picks) + tail
    assert packed.join(np.array(picks, np.int64), sep, (head, tail)) == joined


@given(
    st.lists(st.lists(st.tuples(st.binary(max_size=20), st.booleans()), max_size=20), min_size=1, max_size=4)
)
def test_gather_keeps_the_masked_parts_in_order(packs):
    gathered = Packed.gather(
        [Packed.of([part for part, _ in pack]) for pack in packs],
        [np.array([keep for _, keep in pack], bool) for pack in packs],
    )
    kept = [part for pack in packs for part, keep in pack if keep]
    assert [gathered[i] for i in range(len(gathered))] == kept


@given(
    st.lists(st.sampled_from("abcdefgh"), min_size=1, max_size=20),
    st.lists(st.sampled_from("abcdefghij"), max_size=20),
)
def test_merge_upserts_each_id_where_it_first_stood_with_its_last_content(first, second):
    tables = [
        ItemTable.of(
            ids,
            np.array([[k, 0, k, 0] for k in range(n, n + len(ids))], float),
            [f"{i}{k}".encode() for k, i in enumerate(ids, n)],
        )
        for ids, n in ((first, 0), (second, 100))
    ]
    merged = ItemTable.merge(tables)
    everything = [*enumerate(first), *enumerate(second, 100)]
    order = list(dict.fromkeys(i for _, i in everything))  # each id where it first stood
    last = {i: k for k, i in everything}  # ... with what came last
    assert [merged.item_id(p) for p in range(len(merged))] == order
    assert [merged.bodies[p] for p in range(len(merged))] == [f"{i}{last[i]}".encode() for i in order]
    assert merged.boxes[:, 0].tolist() == [float(last[i]) for i in order]
    assert all(merged.position(i) == p for p, i in enumerate(order))


@given(
    ids=st.lists(st.sampled_from("abcdefghijkl"), unique=True, max_size=12),
    edits=st.lists(
        st.tuples(st.sampled_from("abcdefghijklmnop"), st.booleans(), st.integers(0, 99)),
        unique_by=lambda e: e[0],
        max_size=12,
    ),
    data=st.data(),
)
def test_a_table_edited_is_the_merge_of_it_in_document_order_with_the_edits(
    ids, edits, data, tmp_path_factory
):
    """What a compaction folds (``folded``: the table's items taken in document order, the
    edits put in, with a spill directory each column in files there) is what the store's
    merge of the same makes: each put where its id stood
    (or after the rest, in order), each deletion gone."""
    n = len(ids)
    table = ItemTable.of(
        ids, np.array([[k, 0, k, 0] for k in range(n)], float), [f"{i}!".encode() for i in ids]
    )
    rank = np.array(data.draw(st.permutations(range(n))), np.int64) if data.draw(st.booleans()) else None
    stored = [
        (i, 7, (v, 1.0, v, 1.0), f"{i}{v}".encode()) if put else (i, 7, None, None)
        for i, put, v in edits
        if put or i in ids
    ]
    in_order = table if rank is None else table.take(np.argsort(rank))
    puts = [e for e in stored if e[3] is not None]
    merged = ItemTable.merge(
        [
            in_order,
            ItemTable.of(
                [e[0] for e in puts], np.array([e[2] for e in puts]).reshape(-1, 4), [e[3] for e in puts]
            ),
        ],
        deleted=[e[0] for e in stored if e[3] is None],
    )
    step = data.draw(st.sampled_from([STEP_BYTES, 32, 96]))  # a pass's bytes a step: a row or three
    # ... and a window: a box or three
    window = data.draw(st.sampled_from([MemoryBudget().window_bytes, 32, 96]))
    spill = tmp_path_factory.mktemp("spill") if data.draw(st.booleans()) else None
    if spill is not None and data.draw(st.booleans()):  # a base's columns, mapped: taken through buckets
        table = ItemTable.merge([table]).spilled(spill)
    with mock.patch("spatial.paging.STEP_BYTES", step), MemoryBudget(window_bytes=window).held():
        edited = folded(table, stored, rank, spill)
    assert (mapping(edited.boxes) is not None) == (spill is not None and len(edited) > 0)
    assert [edited.item_id(p) for p in range(len(edited))] == [merged.item_id(p) for p in range(len(merged))]
    assert [bytes(edited.bodies[p]) for p in range(len(edited))] == [
        bytes(merged.bodies[p]) for p in range(len(merged))
    ]
    assert np.array_equal(edited.boxes, merged.boxes)


def test_a_compactions_copy_holds_a_step_of_the_mapped_boxes_not_all_of_them(tmp_path):
    """``folded`` copies the boxes of a table mapped from a file (a base's) in the order they
    lie, handing each step's pages back: a copy in document order would read them all at
    random and hold them all (32 bytes an item) through the copy. The pages read before it
    (an open's, its edits') go back first. Watched at each step, once copied, before its
    pages go back (a thread's samples, under load, could miss the copy)."""
    n = 1 << 20  # 32 MB of boxes; steps of 1 MB
    path = tmp_path / "boxes"
    rng = np.random.default_rng(7)
    expected = rng.random((n, 4))
    path.write_bytes(expected.tobytes())
    with open(path, "rb") as f:
        mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    boxes = np.frombuffer(mapped, np.float64).reshape(n, 4)
    table = ItemTable(Packed.of([b'"i"'] * n), Packed.of([b"{}"] * n), boxes)
    rank = rng.permutation(n)
    assert boxes.sum() == expected.sum()  # every page read, as an open's reads may have
    held = [mapped_bytes(path)]
    release_rows = app.folding.release_rows

    def step_done(view: np.ndarray) -> None:  # a step of the boxes copied: what it holds
        if mapping(view) is mapped:
            held.append(mapped_bytes(path))
        release_rows(view)

    with mock.patch("spatial.paging.STEP_BYTES", 1 << 20), mock.patch("app.folding.release_rows", step_done):
        edited = folded(table, [], rank)
    assert held[0] >= boxes.nbytes * 0.9, held[0]  # the watch sees the pages read
    assert len(held) > 3 and max(held[1:]) < boxes.nbytes / 4, (len(held), max(held[1:]))
    order = np.argsort(rank)
    assert np.array_equal(edited.boxes, expected[order])


@given(ids=st.lists(st.text(max_size=6), max_size=40), halved=st.booleans())
def test_a_spilled_table_is_the_same_table_its_columns_mapped_from_a_file(ids, halved, tmp_path_factory):
    """``spilled`` moves the ids, the bodies' offsets, the id index and the boxes to a file,
    mapped: the same items, found at the same positions, with the same boxes; a table whose
    columns are mapped already is left as it is."""

    boxes = np.arange(4 * len(ids), dtype=float).reshape(-1, 4)
    table = ItemTable.merge([ItemTable.of(ids, boxes, [f'{{"n":{k}}}'.encode() for k in range(len(ids))])])
    if halved:
        table.halve_hashes()
    spilled = table.spilled(tmp_path_factory.mktemp("spill"))
    columns = (spilled.ids.array, spilled.ids.offsets, spilled.bodies.offsets, *spilled._index, spilled.boxes)
    assert all(mapping(column) is not None for column in columns)
    assert [spilled.item_id(p) for p in range(len(spilled))] == [table.item_id(p) for p in range(len(table))]
    assert [bytes(spilled.bodies[p]) for p in range(len(spilled))] == [
        table.bodies[p] for p in range(len(table))
    ]
    assert all(spilled.position(i) == table.position(i) for i in ids)
    assert spilled.boxes.tobytes() == table.boxes.tobytes() and spilled.boxes.shape == (len(table), 4)
    assert spilled.spilled(tmp_path_factory.mktemp("again")) is spilled
    spilled.release()  # its pages handed back: read again, the same
    assert all(spilled.position(i) == table.position(i) for i in ids)


def test_a_packed_import_keeps_its_columns_in_files_not_in_memory(tmp_path, monkeypatch):
    """What an import packs with a spill directory holds its columns (bodies, ids, boxes,
    offsets, id index) in files the kernel pages, none in memory: the builds' peaks hold none
    (its id index too, made in memory when small, as here)."""
    from app.documents import pack
    from app.items import decode_ndjson

    monkeypatch.setattr(app.packed, "SCRATCH_IN_MEMORY", 1 << 16)  # as an import makes them

    lines = "\n".join(f'{{"id":"i{k}","x0":{k},"y0":0,"x1":{k + 1},"y1":1}}' for k in range(500))
    table = pack(decode_ndjson(io.BytesIO(lines.encode()), 1 << 12, 1 << 8), tmp_path)
    columns = (table.ids.array, table.ids.offsets, table.bodies.array, table.bodies.offsets, *table._index)
    assert all(mapping(column) is not None for column in (*columns, table.boxes))
    assert table.position("i499") == 499 and table.item_id(7) == "i7"
    assert table.boxes.tolist() == [[k, 0, k + 1, 1] for k in range(500)]


def test_an_imports_merge_into_itself_holds_none_of_its_id_index(tmp_path):
    """An import merged into itself (``Document._merged``: ``merge``, then ``halve_hashes``)
    reads its whole id index, mapped from a spill: those pages are handed back once read, and
    the halved hashes are made into a file a step at a time, not memory. The table it merged
    lives on through the build (its caller holds it): each held 12 bytes an item, 1.2 GB at
    1e8 items, through every phase."""
    from app.documents import pack
    from app.items import decode_ndjson

    n = 200_000
    lines = "\n".join(f'{{"id":"i{k}","x0":{k},"y0":0,"x1":{k + 1},"y1":1}}' for k in range(n))
    table = pack(decode_ndjson(io.BytesIO(lines.encode()), 1 << 24, 1 << 8), tmp_path)
    expected = app.table.high_halves(np.array(table._index[0]))
    table.release()
    merged = ItemTable.merge([table], spill=tmp_path)
    merged.halve_hashes(tmp_path)
    assert mapped_bytes(tmp_path) == 0  # the hashes read whole (1.6 MB), handed back
    hashes, _ = merged._index
    assert mapping(hashes) is not None and np.array_equal(hashes, expected)
    assert merged.position("i123457") == 123_457 and merged.position("j") is None
