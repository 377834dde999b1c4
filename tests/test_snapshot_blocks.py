"""Snapshot files checked a block at a time: an open reads the header, not the arrays, and a
byte flipped anywhere in the arrays is found by the first read of its block, never answered,
and the base built again from the store."""

import io
import itertools
import json
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import orjson
import pytest
from service import item_json, mapped_bytes

from app.answers import View, change, viewport
from app.blocks import BLOCK, SnapshotCorrupt
from app.cli import main
from app.items import decode_ndjson
from app.registry import Registry
from app.search import search
from app.snapfile import SnapshotFiles, read
from app.stores import SQLiteStore
from app.table import fnv1a
from spatial import scenes

WHOLE = (-1e6, -1e6, 1e6, 1e6)


def _ndjson(pages: int = 4) -> bytes:
    """A few pages of the long document, its words with text to search."""
    boxes, kinds = scenes.long_document(pages=pages, seed=5)
    lines = []
    for i, (box, kind) in enumerate(zip(boxes.tolist(), kinds.tolist(), strict=True)):
        item = dict(zip(("x0", "y0", "x1", "y1"), box, strict=True)) | {"id": f"i{i}", "z": i % 5}
        item["kind"] = scenes.KINDS[kind]
        if item["kind"] == "word":
            item["data"] = {"text": f"w{i % 40} shared"}
        lines.append(json.dumps(item))
    return "\n".join(lines).encode()


@pytest.fixture(scope="module")
def sound(tmp_path_factory):
    """A store with one document, and its snapshot file's bytes: ``(directory, doc_id, bytes)``."""
    directory = tmp_path_factory.mktemp("blocks")
    store = SQLiteStore(directory)
    try:
        registry = Registry(store, SnapshotFiles(directory / "snapshots"), 1 << 30)
        doc = registry.create("d")
        doc.import_items(decode_ndjson(io.BytesIO(_ndjson()), 1 << 16, 1 << 12))
        doc_id = doc.id
    finally:
        store.close()
    (path,) = (directory / "snapshots").glob("*.vsnap")
    return directory, doc_id, path.read_bytes()


def _reads(doc) -> list:
    """Every kind of read a request makes of a snapshot, each answer as plain data: the tree
    walk and the bodies (a viewport), the ids (a diff's leave list), every band of the overview
    with masks, the text (a search), the id index (positions), the table's boxes, and each
    band's aggregates removed by id."""
    n = len(doc.snapshot.tree)
    ids = [f"i{i}" for i in range(0, n, 97)]
    overview = doc.snapshot.overview
    reads = [
        lambda s: viewport(s, View(WHOLE), cap=10**6),
        lambda s: change(s, View((0, 0, 1, 1)), None, cap=10**6).json(),
        lambda s: [(h.positions, h.box) for h in search(s, "shared", 10**4).hits],
        lambda s: [s.position(i) for i in ids],
        lambda s: s.table.positions([*ids, "absent"]),  # looked up together (an open's catch-up)
        lambda s: s.item_boxes(np.arange(n)).tolist(),
    ]
    for band in range(overview.lo, overview.hi + 1):  # one screen of every band, masks and all
        scale = 1.0 / overview.threshold(band)
        reads.append(lambda s, scale=scale: viewport(s, View.of(WHOLE, "rect", scale, 1.0), cap=10**6))
        reads.append(lambda s, band=band: _every_other_removed(s.overview._tree(band)))
    return reads


def _every_other_removed(tree) -> list:
    """A band's tree with every other aggregate removed by id at once (an open taking its saved
    edits), queried whole."""
    if tree is None:
        return []
    none = {"ids": np.empty(0, np.int64), "boxes": np.empty((0, 4))}
    return tree.with_edits({"removed": np.arange(0, len(tree), 2), **none}).query(WHOLE).tolist()


def _open(directory: Path, doc_id: str):
    store = SQLiteStore(directory)
    files = SnapshotFiles(directory / "snapshots")
    return store, files, Registry(store, files, 1 << 30)[doc_id]


def test_an_open_reads_the_header_not_the_arrays(sound):
    directory, doc_id, data = sound
    (path,) = (directory / "snapshots").glob("*.vsnap")
    io_before = _read_bytes()
    _, _, size, blocks = read(path)
    read_at_open = _read_bytes() - io_before
    assert size == len(data) > 32 * BLOCK  # a file of some size
    assert read_at_open < 16 * 1024 and blocks.checked == 0 and not blocks.marks.any()
    store, _, doc = _open(directory, doc_id)
    try:
        blocks = doc.snapshot.blocks
        overview = doc.snapshot.overview
        # Opening the document checked the blocks of its trees' shapes (a few numbers), no more
        assert blocks is not None and blocks.checked <= 2 * BLOCK * (overview.hi - overview.lo + 2)
        opened = blocks.checked
        viewport(doc.snapshot, View((0, 0, 200, 200)), cap=1000)
        assert 0 < blocks.checked - opened < len(data) // 4  # a small viewport checks what it read
    finally:
        store.close()


def test_a_documents_description_checks_its_trees_root_not_the_tree(sound):
    """Its bounds are the root's box: one block checked (checking every block of the tree,
    as it did, took ~90 s at the end of a 1e8-item import)."""
    directory, doc_id, _ = sound
    store, _, doc = _open(directory, doc_id)
    try:
        blocks = doc.snapshot.blocks
        before = blocks.checked
        bounds = doc.describe()["bounds"]
        assert blocks.checked - before <= BLOCK
        boxes = np.array(
            [[i[k] for k in ("x0", "y0", "x1", "y1")] for i in map(json.loads, _ndjson().splitlines())]
        )
        assert bounds == (*boxes[:, :2].min(axis=0).tolist(), *boxes[:, 2:].max(axis=0).tolist())
    finally:
        store.close()


def _imported(directory: Path, lines: Iterable[str]) -> str:
    """A new store in ``directory`` with one document of the NDJSON ``lines``: its id."""
    store = SQLiteStore(directory)
    try:
        doc = Registry(store, SnapshotFiles(directory / "snapshots"), 1 << 30).create("d")
        doc.import_items(decode_ndjson(io.BytesIO("\n".join(lines).encode()), 1 << 16, 1 << 12))
        return doc.id
    finally:
        store.close()


def _read_bytes() -> int:
    """Bytes this process has read through read() and its kin (not through a map)."""
    line = next(x for x in Path("/proc/self/io").read_text().splitlines() if x.startswith("rchar"))
    return int(line.split()[1])


@pytest.mark.slow(seconds=40)  # ~300 places, each opened, read and rebuilt
def test_a_flipped_byte_in_any_array_is_found_by_its_first_read_then_rebuilt(sound, caplog):
    directory, doc_id, data = sound
    (path,) = (directory / "snapshots").glob("*.vsnap")
    _, _, _, blocks = read(path)
    store, _, doc = _open(directory, doc_id)
    reads = _reads(doc)
    expected = [r(doc.snapshot) for r in reads]
    store.close()
    places = sorted(
        {blocks.start + at for lo, hi, _ in blocks.names if hi > lo for at in (lo, (lo + hi) // 2, hi - 1)}
    )
    unfound = 0
    for place in places:
        damaged = bytearray(data)
        damaged[place] ^= 0x20
        path.write_bytes(damaged)
        store, files, doc = _open(directory, doc_id)
        try:
            found = files.rebuilt == 1  # in a block the open reads (the trees' shapes): rebuilt at once
            for read_it, sound_answer in zip(reads, expected, strict=True):
                try:
                    answer = read_it(doc.snapshot)
                except SnapshotCorrupt:
                    found = True
                    continue
                within = [name for lo, hi, name in blocks.names if lo <= place - blocks.start < hi]
                assert _same(answer, sound_answer), f"a flipped byte {place} (in {within}) served"
            if not found:  # no read used that byte (a box of a node every read took whole, say)
                with pytest.raises(SnapshotCorrupt):
                    doc.snapshot.blocks.check_all()  # as `vantage check` does
            unfound += not found
            assert f"bytes {(place - blocks.start) // BLOCK * BLOCK}-" in caplog.text  # the log names it
            assert files.rebuilt == 1 or doc.snapshot.broken
            doc.refresh()  # what the registry does before the next request
            assert not doc.snapshot.broken and files.rebuilt == 1
            assert all(_same(r(doc.snapshot), a) for r, a in zip(reads, expected, strict=True))
        finally:
            store.close()
        (path,) = (directory / "snapshots").glob("*.vsnap")  # the rebuilt file, sound
        assert path.read_bytes() == data
        caplog.clear()
    assert unfound <= len(places) // 20  # nearly every byte of every array is read by some answer


def _same(a, b) -> bool:
    """Whether two answers are the same, the signs of zeros too: by orjson, as
    json.dumps took a fifth of the test's time."""
    return a == b if isinstance(a, bytes) else orjson.dumps(a) == orjson.dumps(b)


def test_vantage_check_reads_every_block_and_removes_a_corrupt_file(sound, capsys):
    directory, doc_id, data = sound
    (path,) = (directory / "snapshots").glob("*.vsnap")
    _, _, _, blocks = read(path)
    main(["check", "--data-dir", str(directory)])
    assert f"{doc_id} 'd': {path.name} sound, " in capsys.readouterr().out
    _, hi, _ = next(x for x in blocks.names if x[2] == "overview.homes")  # no request reads it unasked
    damaged = bytearray(data)
    damaged[blocks.start + hi - 1] ^= 1
    path.write_bytes(damaged)
    with pytest.raises(SystemExit) as exit:
        main(["check", "--data-dir", str(directory)])
    out = capsys.readouterr().out
    assert exit.value.code == 1 and f"{doc_id} 'd': corrupt, " in out and "overview.homes" in out
    assert not path.exists()  # removed: the next open builds it from the store
    store, _, doc = _open(directory, doc_id)
    try:
        assert len(doc.snapshot.tree) > 0 and path.read_bytes() == data
    finally:
        store.close()


def test_an_id_looked_up_checks_the_blocks_its_search_reads_not_the_whole_index(tmp_path):
    """The first lookup of an id in the table after an open costs O(log n) blocks, whatever
    the size (a GET or PATCH of an item, an edit); whether the tree holds it, its ids."""
    n = 60_000
    lines = (json.dumps({"id": f"k{i}", "x0": i, "y0": 0, "x1": i + 1, "y1": 1}) for i in range(n))
    doc_id = _imported(tmp_path, lines)
    store, _, doc = _open(tmp_path, doc_id)
    try:
        table, blocks = doc.snapshot.table, doc.snapshot.blocks
        whole = sum(a.nbytes for a in table._index)
        for item_id in ("k0", "k31337", f"k{n - 1}", "absent"):
            before = blocks.checked
            pos = table.position(item_id)
            assert pos == (None if item_id == "absent" else int(item_id[1:]))
            assert blocks.checked - before < whole // 8, item_id  # a search's blocks: ~20 of 240
        assert table.item_id(31337) == "k31337"
        tree = doc.snapshot.tree
        before = blocks.checked
        assert doc.snapshot.position("k5") == 5 and tree.get(5) == (5.0, 0.0, 6.0, 1.0)
        # The id index's search and one box: a file's tree stores no ids (they are its slots),
        # so whether it holds one reads none, nor its nodes and boxes
        assert blocks.checked - before < 8 * len(tree) // 2
    finally:
        store.close()


def test_ids_looked_up_together_past_a_corrupt_entry_of_the_index_are_not_served_missing(tmp_path):
    """A lookup of many ids at once searches the index unchecked, then checks the two entries
    each search ended between: one that a corrupt entry sent the wrong way is found out, never
    answered "not there"."""
    n = 60_000
    lines = (json.dumps({"id": f"k{i}", "x0": i, "y0": 0, "x1": i + 1, "y1": 1}) for i in range(n))
    doc_id = _imported(tmp_path, lines)
    (path,) = (tmp_path / "snapshots").glob("*.vsnap")
    _, _, _, blocks = read(path)
    (start,) = [lo for lo, hi, name in blocks.names if name == "index.hashes"]
    data = bytearray(path.read_bytes())
    # The block of every search's first probe, zeroed: a search for a hash below it turns above
    # it, and lands on the sound block past it (the entry before unread)
    lo = (start + 4 * (n // 2)) // BLOCK * BLOCK
    data[blocks.start + lo : blocks.start + lo + BLOCK] = bytes(BLOCK)
    path.write_bytes(data)
    store, _, doc = _open(tmp_path, doc_id)
    try:
        with pytest.raises(SnapshotCorrupt):
            doc.snapshot.table.positions([f"k{i}" for i in range(0, n, 300)])
    finally:
        store.close()


def test_a_diffs_leave_list_is_not_served_from_a_corrupt_block_of_ids(sound, tmp_path, caplog):
    """A diff's leave list is the ids of the items that left, joined straight from the file
    (no other read of the answer touches them): a flipped byte among them is found by the
    join, the answer not given."""
    import shutil

    from app.answers import diff_answer
    from app.config import Settings

    directory, doc_id, _ = sound
    shutil.copytree(directory, tmp_path / "copy")
    directory = tmp_path / "copy"
    (path,) = (directory / "snapshots").glob("*.vsnap")
    _, _, _, blocks = read(path)
    lo, hi = next((lo, hi) for lo, hi, name in blocks.names if name == "ids.buffer")
    data = bytearray(path.read_bytes())
    data[blocks.start + (lo + hi) // 2] ^= 0x20
    path.write_bytes(data)
    store, _, doc = _open(directory, doc_id)
    try:
        assert not doc.snapshot.blocks.marks[(lo + hi) // 2 // BLOCK]  # not read yet
        every = ",".join(map(str, WHOLE))
        with pytest.raises(SnapshotCorrupt):  # all leave: every id is in the list
            diff_answer(doc, Settings(data_dir=directory), every, "2e6,2e6,2e6,2e6", limit=10**5)
        assert "ids.buffer" in caplog.text
    finally:
        store.close()


def test_ids_whose_hashes_a_file_keeps_alike_are_each_found(tmp_path):
    """A file keeps the high half of each id's hash: "c58198" and "c125868" share theirs, and
    each is still found (and an absent id beside them is not), before and after an edit."""
    twins = ["c58198", "c125868"]
    lines = [
        json.dumps({"id": item_id, "x0": k, "y0": 0, "x1": k + 1, "y1": 1}) for k, item_id in enumerate(twins)
    ]
    lines += [json.dumps({"id": f"o{k}", "x0": k, "y0": 5, "x1": k + 1, "y1": 6}) for k in range(500)]
    doc_id = _imported(tmp_path, lines)
    store, _, doc = _open(tmp_path, doc_id)
    try:
        hashes, _ = doc.snapshot.table._index
        keys = [
            fnv1a(np.frombuffer(json.dumps(t).encode(), np.uint8), np.array([0, len(t) + 2]))[0]
            for t in twins
        ]
        assert hashes.dtype == np.uint32 and keys[0] != keys[1] and keys[0] >> 32 == keys[1] >> 32
        for k, item_id in enumerate(twins):
            item = json.loads(bytes(doc.snapshot.item_json(doc.snapshot.position(item_id))))
            assert (item["id"], item["x0"]) == (item_id, k)
        assert doc.snapshot.position("c1") is None
        doc.edit(
            [
                (
                    twins[1],
                    (9.0, 9.0, 10.0, 10.0),
                    json.dumps({"id": twins[1], "x0": 9, "y0": 9, "x1": 10, "y1": 10}).encode(),
                )
            ]
        )
        assert doc.snapshot.tree.get(doc.snapshot.position(twins[1])) == (9.0, 9.0, 10.0, 10.0)
        assert doc.snapshot.tree.get(doc.snapshot.position(twins[0])) == (0.0, 0.0, 1.0, 1.0)
    finally:
        store.close()


def test_the_file_and_the_store_keep_each_box_once_and_no_slot_at_all(tmp_path):
    """Every box is in the file once (the table's, the tree's, and each band's aggregates are
    its tree's), the tree's ids are its slots and stored nowhere, and the store's rows hold
    no box: each is read back from its item's JSON, exactly."""
    boxes = scenes.uniform(20_000, seed=12)[0]
    lines = [item_json(f"u{i}", b).decode() for i, b in enumerate(boxes.tolist())]
    doc_id = _imported(tmp_path, lines)
    (path,) = (tmp_path / "snapshots").glob("*.vsnap")
    _, arrays, _, _ = read(path)
    assert "tree.ids" not in arrays
    boxes_like = {a.ctypes.data for a in arrays.values() if a.ndim == 2 and a.shape[1] == 4}
    bands = [name for name in arrays if name.endswith(".tree.boxes") and name.startswith("overview.")]
    assert bands and len(boxes_like) == 1 + len(bands), "a box array written twice"
    store = SQLiteStore(tmp_path)
    try:
        assert store._rows("SELECT max(length(boxes)) FROM bases")[0][0] == 0
        base = store.read_base(doc_id)
        assert base.boxes.tobytes() == boxes.tobytes()  # in the import's order, exactly
    finally:
        store.close()


def test_a_screens_items_lie_together_in_the_file_in_any_import_order(tmp_path):
    """A file lays its items out in the tree's order, not the import's: a screen's bodies are
    a few runs of blocks, so a first answer reads a few blocks (one each item, scattered,
    before); the answers, and the document's order, are the import's."""
    rng = np.random.default_rng(3)
    n = 40_000
    corners = rng.uniform(0, 4000, (n, 2))
    lines = [
        json.dumps({"id": f"s{i}", "x0": x, "y0": y, "x1": x + 5, "y1": y + 5, "data": {"text": f"t{i % 7}"}})
        for i, (x, y) in enumerate(corners.tolist())
    ]
    doc_id = _imported(tmp_path, lines)
    store, _, doc = _open(tmp_path, doc_id)
    try:
        snap, blocks = doc.snapshot, doc.snapshot.blocks
        lo, hi = next((lo, hi) for lo, hi, name in blocks.names if name == "bodies.frames")
        x0, y0, x1, y1 = screen = (1000, 1000, 1400, 1400)  # ~400 items of 40k
        found = [item["id"] for item in json.loads(viewport(snap, View(screen), cap=10**6))["items"]]
        inside = {
            f"s{i}"
            for i, (x, y) in enumerate(corners.tolist())
            if x <= x1 and x + 5 >= x0 and y <= y1 and y + 5 >= y0
        }
        assert set(found) == inside and len(inside) > 300
        read = int((blocks.marks[lo // BLOCK : (hi - 1) // BLOCK + 1] != 0).sum())
        assert read < len(inside) // 4, f"{read} blocks of bodies read for {len(inside)} items"
        # The document's order is still the import's: an export's, a search's, a merge's
        everywhere = snap.in_document_order(snap.tree.query((0, 0, 1e4, 1e4)))
        assert [json.loads(line)["id"] for line in snap.ndjson(everywhere).splitlines()] == [
            f"s{i}" for i in range(n)
        ]
        hits = search(snap, "t3", 10**4).hits
        assert [snap.item_id(h.positions[0]) for h in hits] == [f"s{i}" for i in range(3, n, 7)][: len(hits)]
        moved = [11, 1000, 20_001, 30_002, 39_999]  # edited items keep their places
        box = {"x0": 0, "y0": 0, "x1": 1, "y1": 1, "data": {"text": "t3 again"}}
        doc.edit(
            [(f"s{i}", (0.0, 0.0, 1.0, 1.0), json.dumps({"id": f"s{i}", **box}).encode()) for i in moved]
        )
        hits = search(doc.snapshot, "t3", 10**5).hits
        expected = [f"s{i}" for i in sorted({*range(3, n, 7), *moved})]
        assert [doc.snapshot.item_id(h.positions[0]) for h in hits] == expected[: len(hits)]
        table = snap.document_table()
        assert [table.item_id(i) for i in range(0, n, 997)] == [f"s{i}" for i in range(0, n, 997)]
    finally:
        store.close()


def test_a_first_answer_reads_from_the_disk_about_what_it_checks(tmp_path):
    """A mapped file is read a page a fault (not the device's read-ahead around each: 8 MiB
    here, which made a first answer read ~130 MB of a 10M-item file), and what a read needs
    is fetched at once: the open and a first viewport read a few times the blocks checked."""
    boxes, _ = scenes.uniform(150_000, seed=8)
    lines = (
        json.dumps({"id": f"u{i}", "x0": x0, "y0": y0, "x1": x1, "y1": y1})
        for i, (x0, y0, x1, y1) in enumerate(boxes.tolist())
    )
    doc_id = _imported(tmp_path, lines)
    (path,) = (tmp_path / "snapshots").glob("*.vsnap")
    with open(path, "rb") as file:  # out of the page cache: the next reads go to the disk
        os.posix_fadvise(file.fileno(), 0, 0, os.POSIX_FADV_DONTNEED)
    before = _disk_bytes()
    store, _, doc = _open(tmp_path, doc_id)
    try:
        x0, y0 = boxes[:, :2].min(axis=0)
        viewport(doc.snapshot, View((x0, y0, x0 + 1920, y0 + 1080)), cap=10**6)
        read, checked = _disk_bytes() - before, doc.snapshot.blocks.checked
        assert checked > 0 and read < 4 * checked + (1 << 20) < path.stat().st_size // 4, (read, checked)
    finally:
        store.close()


def _disk_bytes() -> int:
    """Bytes this process has had read from the disk (read() and page faults alike)."""
    line = next(x for x in Path("/proc/self/io").read_text().splitlines() if x.startswith("read_bytes"))
    return int(line.split()[1])


def test_an_import_writes_its_base_a_part_at_a_time_letting_each_go_before_the_next(tmp_path, monkeypatch):
    """An import builds its base straight into its file: the overview's arrays are let go
    before the tree is built, and the tree's before the items' frames are made, so the whole
    base is never held at once; its arrays are those ``save`` writes of the base built in
    memory."""
    import weakref

    import app.basefile
    import app.snapfile
    from app.documents import pack
    from app.snapshots import build

    table = pack(decode_ndjson(io.BytesIO(_ndjson()), 1 << 16, 1 << 12), tmp_path)
    written: list[tuple[str, weakref.ref]] = []
    trees: list[np.ndarray] = []
    add, build_arrays, framed = (
        app.snapfile.Writer.add,
        app.basefile.QuadTree.build_arrays,
        app.basefile.framed_arrays,
    )

    def recorded(out, name, array):
        add(out, name, array)
        written.append((name, weakref.ref(array)))

    def held(*prefixes: str) -> list[str]:
        return [
            n for n, ref in written if n.startswith(prefixes) and n != "overview.homes" and ref() is not None
        ]

    def tree_after_the_overview(boxes, *args, **kwargs):
        if boxes is table.boxes:  # the items' tree (the overview's bands build trees too)
            assert written and not held("overview."), held("overview.")
            trees.append(boxes)
        return build_arrays(boxes, *args, **kwargs)

    def frames_after_the_tree(*args, **kwargs):
        assert not held("tree.", "boxes"), held("tree.", "boxes")
        return framed(*args, **kwargs)

    monkeypatch.setattr(app.snapfile.Writer, "add", recorded)
    monkeypatch.setattr(app.basefile.QuadTree, "build_arrays", tree_after_the_overview)
    monkeypatch.setattr(app.basefile, "framed_arrays", frames_after_the_tree)
    app.snapfile.write_base(table, tmp_path / "streamed.vsnap", 3, "b")
    monkeypatch.undo()
    assert len(trees) == 1 and not held("overview.", "tree.")
    app.snapfile.save(build(table, 3, "b"), tmp_path / "built.vsnap")
    (meta, streamed, _, _), (built_meta, arrays, _, _) = (
        read(tmp_path / "streamed.vsnap"),
        read(tmp_path / "built.vsnap"),
    )
    assert meta == built_meta and sorted(streamed) == sorted(arrays)
    for name, array in arrays.items():
        assert streamed[name].dtype == array.dtype and np.array_equal(streamed[name], array), name


def test_a_files_bytes_are_pushed_to_the_disk_as_it_is_written(tmp_path, monkeypatch):
    """Every ``PUSH_BYTES`` of arrays written, the disk is asked to start writing them (not
    waited for), once they are out of the process's buffer: the ``fsync`` that ends the file
    waits for the last of them only. On Linux the call is ``sync_file_range``'s."""
    import sys

    import app.snapformat

    assert sys.platform != "linux" or app.snapformat._start_writeback.__name__ == "start"
    pushed: list[tuple[int, int]] = []
    start = app.snapformat._start_writeback

    def recorded(fd: int, offset: int, length: int) -> None:
        assert os.fstat(fd).st_size >= offset + length  # flushed before it is pushed
        pushed.append((offset, length))
        start(fd, offset, length)

    monkeypatch.setattr(app.snapformat, "PUSH_BYTES", 3 * BLOCK)
    monkeypatch.setattr(app.snapformat, "_start_writeback", recorded)
    arrays = {f"a{k}": np.arange(k % 40 + 1, dtype=np.int64) for k in range(300)}  # some buffered
    with app.snapformat.Writer(tmp_path / "pushed.vsnap") as out:
        for name, array in arrays.items():
            out.add(name, array)
        written = out._size
        out.finish({})
    assert pushed and pushed[0][0] == BLOCK  # the arrays begin at the first block
    assert all(a + n == b for (a, n), (b, _) in itertools.pairwise(pushed))
    assert all(n >= 3 * BLOCK for _, n in pushed)
    assert BLOCK + written - (pushed[-1][0] + pushed[-1][1]) < 3 * BLOCK  # all but the last
    _, got, _, _ = read(tmp_path / "pushed.vsnap")
    assert all(np.array_equal(got[name], array) for name, array in arrays.items())


def test_an_edit_checks_the_blocks_it_reads_as_many_whatever_the_documents_size(tmp_path):
    """An edit of a mapped document reads a few entries of its overview's bands (an item's
    home, each aggregate it changes, a slot) and checks the blocks of those alone: at 1e8
    items, checking each band it touched whole took seconds and GBs. So the blocks it checks
    grow with the tree's depth, not with the document (10x the items here)."""
    from app.blocks import CHECKED
    from app.items import Item, batch_of

    checked = []
    for n in (10_000, 100_000):
        store = SQLiteStore(tmp_path / str(n))
        files = SnapshotFiles(tmp_path / str(n) / "snapshots")
        doc = Registry(store, files, 1 << 30).create("d")
        rng = np.random.default_rng(0)
        xy, size = rng.uniform(0, 1e4, (n, 2)), rng.uniform(1, 50, (n, 2))
        rows = zip(xy.tolist(), size.tolist(), strict=True)
        doc.import_items(
            [batch_of([Item(f"i{k}", x, y, x + w, y + h) for k, ((x, y), (w, h)) in enumerate(rows)], n)]
        )
        doc = Registry(store, files, 1 << 30)[doc.id]  # opened again: mapped from its file
        marks = doc.snapshot.blocks.marks
        before = int((marks == CHECKED).sum())
        moved = batch_of([Item("i5", 100, 100, 130, 120)], 10)
        doc.edit(list(zip(moved.ids, map(tuple, moved.boxes.tolist()), moved.bodies, strict=True)))
        checked.append(int((marks == CHECKED).sum()) - before)
        assert doc.snapshot.item_boxes(np.array([doc.snapshot.position("i5")])).tolist() == [
            [100, 100, 130, 120]
        ]
        store.close()
    # the tree deepens (a level or two more); checking each band whole, 200 and 652 blocks
    assert checked[1] < 2 * checked[0], f"an edit checked {checked} blocks at 10k and 100k items"


def test_a_first_answer_checks_the_entries_of_the_frames_index_it_reads(tmp_path, monkeypatch):
    """The frames' index (where each frame starts, its first item) grows with the document:
    12 MB at 1e8 items, read from the disk and checked whole by a first answer. A join checks
    the entries of the frames it decodes, and the items' offsets, alone."""
    from app import frames
    from app.blocks import CHECKED

    monkeypatch.setattr(frames, "FRAME_BYTES", 256)  # many frames: an index of many blocks
    boxes, _ = scenes.uniform(60_000, seed=9)
    lines = (
        json.dumps({"id": f"u{i}", "x0": x0, "y0": y0, "x1": x1, "y1": y1})
        for i, (x0, y0, x1, y1) in enumerate(boxes.tolist())
    )
    store, _, doc = _open(tmp_path, _imported(tmp_path, lines))
    try:
        snap = doc.snapshot
        x0, y0 = boxes[:, :2].min(axis=0)
        answer = viewport(snap, View((x0, y0, x0 + 1920, y0 + 1080)), cap=10**6)
        assert json.loads(answer)["items"], "a screen of items, read through their frames"
        bodies, blocks = snap.table.bodies, snap.blocks
        shift, *places = blocks.places([bodies.first, bodies.at]).tolist()
        for at, array in zip(places[0::2], (bodies.first, bodies.at), strict=True):
            lo, hi = at >> shift, (at + array.nbytes - 1) >> shift
            checked = int((blocks.marks[lo : hi + 1] == CHECKED).sum())
            assert hi - lo + 1 >= 8 and checked <= (hi - lo + 1) // 4, (checked, hi - lo + 1)
    finally:
        store.close()


def test_an_item_of_a_frame_already_decoded_is_not_served_past_its_unchecked_offsets(tmp_path, monkeypatch):
    """A join whose items' frames are decoded copies them from the arena at once: their
    offsets' blocks must be checked first all the same. An item whose frame another item's
    answer decoded, but whose offsets lie in a block no answer read yet, damaged there, is
    refused, never copied from where its damaged offsets say."""
    from app import frames

    monkeypatch.setattr(frames, "FRAME_BYTES", 1 << 16)  # a frame's offsets span blocks
    lines = (json.dumps({"id": f"n{i}", "x0": i, "y0": 0, "x1": i + 1, "y1": 1}) for i in range(5_000))
    doc_id = _imported(tmp_path, lines)
    (path,) = (tmp_path / "snapshots").glob("*.vsnap")
    _, _, _, blocks = read(path)
    store, _, doc = _open(tmp_path, doc_id)
    try:
        bodies = doc.snapshot.table.bodies
        assert isinstance(bodies, frames.Framed)
        shift, at, row = doc.snapshot.blocks.places([bodies.offsets]).tolist()
        last = int(bodies.first[1]) - 1  # frame 0's last item
        assert (at + 2 * row) >> shift < (at + last * row) >> shift, "its offsets in another block"
        assert json.loads(bodies.join(np.array([0])))["id"] == "n0"  # frame 0 decoded
        with open(path, "r+b") as file:  # the mapped file, damaged in place
            file.seek(blocks.start + at + (last + 1) * row)
            file.write(b"\x7f")
        with pytest.raises(SnapshotCorrupt):
            bodies.join(np.array([last]))
    finally:
        store.close()


def test_a_long_run_of_edits_hands_back_the_pages_of_the_file_its_reads_mapped(sound, tmp_path):
    """An open with edits pending applies them all at once (``with_edits``). Each edit reads a
    few rows of the base's file, and each read maps the folio of pages around it (up to a few
    MB: 1,000 edits held ~1 GB of a 1e7-item file). They go back every ``RELEASE_AFTER``
    edits: the file read whole before a run of that many is no longer mapped after it."""
    from app.snapfile import load
    from app.snapshots import RELEASE_AFTER

    _, _, data = sound
    path = tmp_path / "base.vsnap"
    path.write_bytes(data)
    meta = read(path)[0]
    snap = load(path, meta["base_id"], meta["version"])
    mapped = snap.blocks._mapped
    assert sum(mapped[k] for k in range(0, len(mapped), 4096)) >= 0  # every page read: all mapped
    whole = mapped_bytes(path)
    assert whole >= len(data) * 0.9, (whole, len(data))
    boxes = snap.tree.get(snap.position("i0"))
    edits = [
        (f"i{k}", meta["version"] + 1, boxes, item_json(f"i{k}", boxes, kind="word"))
        for k in range(RELEASE_AFTER)
    ]
    edited, _ = snap.with_edits(edits)
    assert mapped_bytes(path) < whole / 4, (mapped_bytes(path), whole)
    assert all(edited.tree.get(edited.position(f"i{k}")) == boxes for k in range(RELEASE_AFTER))


@pytest.mark.parametrize(
    "array", ["ids.buffer", "ids.offsets", "bodies.frames", "bodies.offsets", "boxes", "rank"]
)
def test_a_compaction_over_a_corrupt_file_folds_the_stores_rows_instead(sound, tmp_path, array):
    """A compaction reads its base's file whole (its items put back in document order): a
    flipped byte in any of the arrays it reads is found before it is used, and the fold
    takes the base's items from the store instead. The new base holds the same items as a
    compaction over the sound file."""
    import shutil

    directory, doc_id, _ = sound
    moved = (1.0, 2.0, 3.0, 4.0)
    folded = []
    for damaged in (False, True):
        copy = tmp_path / str(damaged)
        shutil.copytree(directory, copy)
        store, _, doc = _open(copy, doc_id)
        for k in range(5):  # stored, then the file damaged: the fold's reads are the first
            doc.edit([(f"i{k}", moved, item_json(f"i{k}", moved, kind="word"))])
        store.close()
        if damaged:
            (path,) = (copy / "snapshots").glob("*.vsnap")
            _, _, _, blocks = read(path)
            lo, hi = next((lo, hi) for lo, hi, name in blocks.names if name == array)
            data = bytearray(path.read_bytes())
            data[blocks.start + (lo + hi) // 2] ^= 0x20
            path.write_bytes(data)
        store, _, doc = _open(copy, doc_id)  # the edits applied again (an open's catch-up)
        try:
            doc.compact()
            table = doc.snapshot.document_table()
            folded.append([(table.item_id(p), bytes(table.bodies[p])) for p in range(len(table))])
        finally:
            store.close()
    assert folded[1] == folded[0]
    assert (folded[0][0][0], json.loads(folded[0][0][1])["x0"]) == ("i0", 1.0)


def test_a_bad_block_found_among_checked_ones_is_refused_again_by_a_read_of_them_all(sound, tmp_path):
    """Once a block is found bad, every later read over it is refused, also a read of a whole
    array whose other blocks are all checked already (the check skips arrays it has seen)."""
    _, _, data = sound
    path = tmp_path / "d.vsnap"
    path.write_bytes(data)
    _, arrays, _, blocks = read(path)
    name, array = max(arrays.items(), key=lambda kv: kv[1].nbytes)
    _, offset, stride = blocks.places([array]).tolist()
    starts = offset + np.arange(len(array)) * stride
    block_of = starts // BLOCK
    whole = block_of == (starts + stride - 1) // BLOCK  # rows within one block
    spanned = np.unique(block_of[whole])
    assert len(spanned) >= 3, f"{name} spans {len(spanned)} blocks"
    bad = int(spanned[len(spanned) // 2])
    damaged = bytearray(data)
    damaged[blocks.start + bad * BLOCK + BLOCK // 2] ^= 0x20
    path.write_bytes(damaged)
    _, arrays, _, blocks = read(path)
    array = arrays[name]
    for block in spanned.tolist():  # a row of each block, one at a time, as scattered reads do
        first = int(np.flatnonzero(whole & (block_of == block))[0])
        row = array[first : first + 1]
        if block == bad:
            with pytest.raises(SnapshotCorrupt):
                blocks.check(row)
        else:
            blocks.check(row)
    for _ in range(2):
        with pytest.raises(SnapshotCorrupt):
            blocks.check(array)


def test_each_set_of_files_keeps_its_documents_decoded_items_within_its_own_limit(sound):
    """``VANTAGE_FRAMES_MB`` is a setting of a server's files, not of the process: two in one
    process keep their own, and answer the same."""
    directory, doc_id, _ = sound
    store = SQLiteStore(directory)
    try:
        answers, held = [], []
        for limit in (0, 1 << 16, 1 << 30):
            files = SnapshotFiles(directory / "snapshots", frames_bytes=limit)
            doc = Registry(store, files, 1 << 30)[doc_id]
            answers.append(viewport(doc.snapshot, View(WHOLE), cap=10**6))
            held.append(files.decoded.bytes)
        assert answers[0] == answers[1] == answers[2]
        assert held[0] == 0 and 0 < held[1] <= 1 << 16 < held[2], held
    finally:
        store.close()
