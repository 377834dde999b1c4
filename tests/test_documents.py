"""Documents against a dict model: imports (upserts), edits and restarts in any order, every
query compared with brute force over the model, and the item table's merge on its own."""

import asyncio
import tempfile
import threading
from pathlib import Path

import msgspec
import numpy as np
import oracle
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    invariant,
    precondition,
    rule,
    run_state_machine_as_test,
)

from app import editfile
from app.answers import View, change, viewport
from app.blocks import SnapshotCorrupt
from app.items import Item, batch_of
from app.registry import Registry
from app.snapfile import SnapshotFiles
from app.stores import open_store
from app.table import ItemTable
from spatial.paging import mapping

IDS = st.sampled_from([f"i{k}" for k in range(40)] + ['é\n"q', "x" * 256])  # repeats force upserts
COORD = st.integers(-50, 50).map(float)
BOXES = st.tuples(COORD, COORD, st.integers(0, 30), st.integers(0, 30)).map(
    lambda b: (b[0], b[1], b[0] + b[2], b[1] + b[3])
)
RECTS = BOXES.map(lambda b: (b[0], b[1], b[2] + 20, b[3] + 20))


def _batch(items: list[tuple[str, tuple]]) -> object:
    return batch_of([Item(item_id, *box, kind="note", z=len(item_id)) for item_id, box in items], 4096)


def _rows(table: ItemTable) -> list[tuple[bytes, bytes, tuple]]:
    boxes = table.read_boxes()
    return [(bytes(table.ids[i]), bytes(table.bodies[i]), tuple(boxes[i])) for i in range(len(table))]


class DocumentMachine(RuleBasedStateMachine):
    def __init__(self, database_url: str | None = None) -> None:
        super().__init__()
        self.dir = tempfile.TemporaryDirectory()
        self.store = open_store(Path(self.dir.name), database_url)  # SQLite, or that PostgreSQL
        self.files = SnapshotFiles(Path(self.dir.name) / "snapshots")
        self.doc_id = Registry(self.store, self.files, 1 << 30).create("model").id
        self.reopen()
        self.model: dict[str, tuple] = {}
        self.version = 0
        self.writers: list[threading.Thread] = []  # edits from other threads (compact_while_others_edit)

    def reopen(self) -> None:
        self.doc = Registry(self.store, self.files, 1 << 30)[self.doc_id]

    @rule(items=st.lists(st.tuples(IDS, BOXES), max_size=30))
    def import_items(self, items):
        count, version = self.doc.import_items([_batch(items[:10]), _batch(items[10:])])
        assert (count, version) == (len(dict(items)), self.version + 1)  # distinct items
        self.version = version
        self.model.update(items)  # later lines win

    @rule(item_id=IDS, box=BOXES)
    def put(self, item_id, box):
        version, created = self.doc.put(_batch([(item_id, box)]))
        assert (version, created) == (self.version + 1, item_id not in self.model)
        self.version = version
        self.model[item_id] = box

    @precondition(lambda self: self.model)
    @rule(data=st.data())
    def delete(self, data):
        item_id = data.draw(st.sampled_from(sorted(self.model)))
        self.version = self.doc.delete(item_id)
        del self.model[item_id]

    @rule()
    def restart(self):
        self.reopen()

    @rule(damage=st.none() | st.integers(0, 10_000))
    def save_the_edits_then_restart(self, damage):
        """An open takes the edits saved beside its base's file as they were made, then the
        store's since (``editfile``): the same document, its zoomed-out aggregates too. A
        damaged file is passed over, and every edit replayed from the store."""
        snap = self.doc.snapshot
        if snap.blocks is None or not snap.edits:  # a base built in memory (no items) has no file
            return
        path = self.files.edits_path(self.doc_id, snap.base_id)
        assert editfile.save(path, snap, self.store, self.doc_id)
        if damage is not None:
            data = bytearray(path.read_bytes())
            data[damage % len(data)] ^= 0xFF
            path.write_bytes(data)
        self.reopen()
        assert (self.doc.edits_saved == (snap.base_id, snap.edits)) == (damage is None)
        if damage is None:
            overview = snap.overview
            for band in range(overview.lo, overview.hi + 1):
                view = View.of((-100, -100, 100, 100), "rect", 1.0 / overview.threshold(band), 1.0)
                assert viewport(self.doc.snapshot, view, cap=1000) == viewport(snap, view, cap=1000)

    @rule(offset=st.integers(0, 10_000))
    def corrupt_a_snapshot_file_then_restart(self, offset):
        """A damaged file is never served: its header's damage is found at the restart, a
        block's by the first read of it (here, a read of every block); either way the base is
        built again from the store."""
        for path in self.files.directory.glob("*.vsnap"):
            data = bytearray(path.read_bytes())
            data[offset % len(data)] ^= 0xFF
            path.write_bytes(data)
        self.reopen()
        blocks = self.doc.snapshot.blocks
        try:
            if blocks is not None:
                blocks.check_all()
        except SnapshotCorrupt:
            self.doc.refresh()  # as the registry does before the document's next request
            assert not self.doc.snapshot.broken

    @rule()
    def compact(self):
        """A compaction folds the stored edits into the base's table it holds (mapped, say),
        not into the base's rows read again: both make the same items, in the same order."""
        with_table = self.doc.snapshot.document_table(None, self.store.edits(self.doc_id))
        assert _rows(with_table) == _rows(self.store.read_items(self.doc_id))
        assert self.doc.compact() == self.version  # the same items: the same version
        assert _rows(self.doc.snapshot.document_table()) == _rows(with_table)

    @rule(edits=st.lists(st.tuples(IDS, st.none() | BOXES), min_size=1, max_size=4), stale=st.booleans())
    def compact_while_others_edit(self, edits, stale):
        """A compaction builds its new base outside the writers' turn: edits made meanwhile (each
        from a thread of its own, which must not wait for the compaction) commit at once and stay,
        applied on the new base. An import meanwhile (``stale``) replaces the base: then the
        compaction stores nothing, and the import's items stand."""
        build = self.files.write

        def while_building(*args):
            del self.files.write  # once: the import below builds its own
            made = build(*args)
            for item_id, box in edits:
                self._edit_from_another_writer(item_id, box)
            if stale:
                self.import_items([("i0", (0.0, 0.0, 1.0, 1.0))])
            return made

        self.files.write = while_building  # the document's: the same object
        pending = self.doc.snapshot.edits
        try:
            version = self.doc.compact()
        finally:  # a writer that waited (the failure) ends before the store closes under it
            for writer in self.writers:
                writer.join()
            self.writers.clear()
        assert version == self.version  # the last edit's or the import's: a compaction adds none
        assert (self.files.write == build) == bool(pending)  # it built once if there was anything to fold
        vars(self.files).pop("write", None)

    def _edit_from_another_writer(self, item_id: str, box: tuple | None) -> None:
        """``item_id`` put at ``box`` (None: deleted, if it is there), from another thread."""
        if box is None and item_id not in self.model:
            return
        done: list[int] = []
        edit = (
            (lambda: self.doc.delete(item_id))
            if box is None
            else (lambda: self.doc.put(_batch([(item_id, box)]))[0])
        )
        writer = threading.Thread(target=lambda: done.append(edit()))
        self.writers.append(writer)
        writer.start()
        writer.join(timeout=20)
        assert done == [self.version + 1], "an edit waited for a compaction's build"
        self.version = done[0]
        if box is None:
            del self.model[item_id]
        else:
            self.model[item_id] = box

    @rule(rect=RECTS)
    def query(self, rect):
        snap = self.doc.snapshot
        ids = sorted(self.model)
        boxes = np.array([self.model[i] for i in ids]).reshape(-1, 4)
        expected = {ids[k] for k in np.flatnonzero(oracle.hits(boxes, rect))}
        found = [msgspec.json.decode(snap.item_json(p)) for p in snap.tree.query(rect).tolist()]
        assert {item["id"] for item in found} == expected
        assert all(
            tuple(item[k] for k in ("x0", "y0", "x1", "y1")) == self.model[item["id"]] for item in found
        )
        answer = msgspec.json.decode(change(snap, View(rect), None, cap=1000).json())
        assert answer["reset"] and {item["id"] for item in answer["enter"]} == expected

    @invariant()
    def describes_the_model(self):
        snap = self.doc.snapshot
        assert snap.version == self.version and len(snap.tree) == len(self.model)
        for item_id in self.model:
            assert snap.item_id(snap.position(item_id)) == item_id

    def teardown(self) -> None:
        self.store.close()
        self.dir.cleanup()


TestDocument = DocumentMachine.TestCase  # on SQLite
TestDocument.pytestmark = [pytest.mark.slow(seconds=25)]  # 60 runs of up to 50 steps


@pytest.mark.slow(seconds=10)
def test_documents_on_postgresql(database_url):
    """The same machine on a real PostgreSQL server (fewer examples: each opens a pool)."""
    run_state_machine_as_test(lambda: DocumentMachine(database_url), settings=settings(max_examples=20))


@given(st.lists(st.lists(IDS, max_size=20), min_size=1, max_size=4), st.lists(IDS, max_size=5))
def test_merging_tables_keeps_the_last_of_each_id_and_drops_the_deleted(groups, deleted):
    tables, model, serial = [], {}, 0
    for ids in groups:
        bodies = []
        for item_id in ids:
            serial += 1
            bodies.append(b"%d" % serial)
            model[item_id] = bodies[-1]
        tables.append(ItemTable.of(ids, np.full((len(ids), 4), float(serial)), bodies))
    for item_id in deleted:
        model.pop(item_id, None)
    merged = ItemTable.merge(tables, deleted=deleted)
    assert {merged.item_id(p): merged.bodies[p] for p in range(len(merged))} == model
    assert len(merged) == len(model)
    for item_id in model:
        assert merged.item_id(merged.position(item_id)) == item_id
    assert merged.position("absent") is None


@settings(max_examples=50)
@given(st.lists(st.lists(IDS, max_size=20), min_size=1, max_size=4), st.lists(IDS, max_size=5))
def test_a_merge_spilled_to_disk_is_the_merge_in_memory(groups, deleted):
    """Bodies gathered and reordered into a spill file, a few bytes a step (each step handing
    its pages back), come out byte for byte as the merge in memory makes them."""
    tables = [
        ItemTable.of(
            ids, np.full((len(ids), 4), float(k)), [b"%s-%d" % (i.encode(), k) * (k + 1) for i in ids]
        )
        for k, ids in enumerate(groups)
    ]
    with tempfile.TemporaryDirectory() as spill, pytest.MonkeyPatch.context() as patch:
        patch.setattr("app.packed.STEP_BYTES", 20)
        on_disk = ItemTable.merge(tables, deleted=deleted, spill=Path(spill))
        in_memory = ItemTable.merge(tables, deleted=deleted)
        assert bytes(on_disk.bodies.buffer) == bytes(in_memory.bodies.buffer)
        assert (on_disk.bodies.offsets == in_memory.bodies.offsets).all()
        assert bytes(on_disk.ids.buffer) == bytes(in_memory.ids.buffer)
        assert (on_disk.boxes == in_memory.boxes).all()
        assert not list(Path(spill).iterdir())  # the spill file never had a name


def test_catching_one_document_up_stalls_no_request_for_another(tmp_path, monkeypatch):
    """Another process writes to document A, whose catching up here is slow (a base rebuilt
    from the store, say): a request for B is answered meanwhile, one for A waits for it."""
    import asyncio
    import threading
    import time

    from app.documents import Document
    from app.stores import SQLiteStore

    store, other = SQLiteStore(tmp_path), SQLiteStore(tmp_path)
    registry = Registry(store, SnapshotFiles(tmp_path / "snapshots"), 1 << 30)
    a, b = registry.create("a"), registry.create("b")
    slow, refresh = threading.Event(), Document.refresh

    def slow_refresh(doc):
        if doc.id == a.id:
            slow.wait(5)
        refresh(doc)

    monkeypatch.setattr(Document, "refresh", slow_refresh)

    async def requests() -> tuple[float, float, int]:
        await registry.refresh()  # what opening said
        with other.writing(a.id) as write:  # another process's edit of A
            write.write_edits(write.bump(), [("n", (0.0, 0.0, 1.0, 1.0), b'{"id":"n"}')], 1, None)
        await asyncio.sleep(0.01)  # a new turn of the event loop: the next request looks
        started = time.monotonic()
        assert await registry.get(b.id) is b
        other_doc = time.monotonic() - started
        asyncio.get_running_loop().call_later(0.3, slow.set)
        got_a = await registry.get(a.id)
        return other_doc, time.monotonic() - started, got_a.snapshot.version

    try:
        other_doc, same_doc, version = asyncio.run(requests())
    finally:
        slow.set()
        store.close()
        other.close()
    # B waiting for A's catching up would take its 5 s: half of it tells them apart on a busy
    # machine (B's first open loads its compiled code too)
    assert other_doc < 2.5 and same_doc >= 0.3 and version == 1


def _saves_finished() -> None:
    """Wait for the saves of edits that closing documents started (``Document.save_edits``,
    each in a thread of its own), before their directory goes."""
    for thread in threading.enumerate():
        if thread.name.startswith("save edits of "):
            thread.join()


OPS = st.lists(
    st.tuples(st.sampled_from(["open", "edit", "import", "pin", "unpin", "delete"]), st.integers(0, 3)),
    max_size=30,
)


@settings(max_examples=25, deadline=None)
@given(OPS)
def test_the_registry_counts_what_its_open_documents_hold(ops):
    """The registry's running count of the open documents' bytes (what keeping to the budget
    reads after every request) is their sum after any opens, edits, imports and closes, and
    documents not in use are closed until it is within the budget (but the most recently
    used: one bigger than the budget alone stays open)."""
    with tempfile.TemporaryDirectory() as tmp:
        store = open_store(Path(tmp))
        try:
            budget = 40_000  # two or three of these documents
            registry = Registry(store, SnapshotFiles(Path(tmp) / "snapshots"), budget)
            ids = [registry.create(f"d{k}").id for k in range(4)]
            pins: list = []
            for op, k in ops:
                if ids[k] is None:
                    continue
                if op == "delete":
                    registry.delete(ids[k])
                    ids[k] = None
                    continue
                doc = registry[ids[k]]
                if op == "edit":
                    doc.put(_batch([(f"e{len(pins)}{k}", (k, 0, k + 1, 1))]))
                elif op == "import":
                    doc.import_items([_batch([(f"i{j}", (j, k, j + 1, k + 1)) for j in range(50)])])
                elif op == "pin":
                    pin = registry.pinned(doc)
                    pin.__enter__()
                    pins.append(pin)
                elif op == "unpin" and pins:
                    pins.pop().__exit__(None, None, None)
                registry.evict()
                open_docs = [registry._open[i] for i in registry._open]
                held = registry.stats()["held_bytes"]
                assert held == sum(d.nbytes for d in open_docs)
                if not any(d.pins for d in open_docs):  # within it, or the most recently used alone
                    assert held <= budget or open_docs == [doc]
        finally:
            _saves_finished()  # closing a document saves its edits in a thread: into ``tmp``
            store.close()


@pytest.mark.parametrize("failing", ["the index", "the rows"])
def test_an_import_whose_index_or_rows_fail_while_both_are_written_stores_nothing(
    open_store, tmp_path, monkeypatch, failing
):
    """The store's rows are staged beside the index's build: when either fails (the build,
    half its file written, once the rows are in; the rows once the file is written), the
    document, its rows and its files stay those of the version before, and the staged rows go."""
    import app.basefile
    from app.errors import StorageFull
    from app.stores import Store

    store = open_store()
    files = SnapshotFiles(tmp_path / "snapshots")
    doc = Registry(store, files, 1 << 30).create("d")
    first = [(f"a{k}", (k, 0.0, k + 1.0, 1.0)) for k in range(50)]
    assert doc.import_items([_batch(first)]) == (50, 1)
    before, kept = _rows(store.read_base(doc.id)), sorted(files.directory.iterdir())
    rows_written, stage_base, framed = threading.Event(), Store.stage_base, app.basefile.framed_arrays

    def rows_then(store, *args):
        if failing == "the rows":
            raise StorageFull("no room for the rows")
        staged = stage_base(store, *args)
        rows_written.set()
        return staged

    def frames_then(*args, **kwargs):
        if failing == "the index":
            assert rows_written.wait(10)  # the rows are staged: they must go again
            raise RuntimeError("the index failed")
        return framed(*args, **kwargs)

    monkeypatch.setattr(Store, "stage_base", rows_then)
    monkeypatch.setattr(app.basefile, "framed_arrays", frames_then)
    second = [(f"b{k}", (0.0, k, 1.0, k + 1.0)) for k in range(80)]
    with pytest.raises(StorageFull if failing == "the rows" else RuntimeError):
        doc.import_items([_batch(second)])
    assert doc.snapshot.version == 1 and store.document(doc.id)["version"] == 1
    assert _rows(store.read_base(doc.id)) == before
    assert store._rows("SELECT count(DISTINCT rowset) FROM bases")[0][0] == 1  # none staged is left
    assert sorted(files.directory.iterdir()) == kept  # the new base's file removed
    monkeypatch.undo()
    snap = Registry(store, files, 1 << 30)[doc.id].snapshot  # opened again: the version before
    assert snap.version == 1 and sorted(snap.item_id(p) for p in range(len(snap.table))) == sorted(
        item_id for item_id, _ in first
    )


def test_an_import_built_again_inside_a_write_whose_rows_fail_stores_nothing(
    open_store, tmp_path, monkeypatch
):
    """An import that another process's write sent back to be built inside one write writes
    the store's rows beside the build: when they fail, the transaction goes, not half of it."""
    from app.documents import Document
    from app.errors import StorageFull
    from app.stores.base import Writing

    store = open_store()
    files = SnapshotFiles(tmp_path / "snapshots")
    doc = Registry(store, files, 1 << 30).create("d")
    first = [(f"a{k}", (k, 0.0, k + 1.0, 1.0)) for k in range(50)]
    doc.import_items([_batch(first)])
    before, kept = _rows(store.read_base(doc.id)), sorted(files.directory.iterdir())

    def no_room(*args):
        raise StorageFull("no room for the rows")

    monkeypatch.setattr(Document, "_import_beside", lambda *args: None)  # another process wrote
    monkeypatch.setattr(Writing, "write_base", no_room)
    with pytest.raises(StorageFull):
        doc.import_items([_batch([(f"b{k}", (0.0, k, 1.0, k + 1.0)) for k in range(80)])])
    monkeypatch.undo()
    assert doc.snapshot.version == 1 and store.document(doc.id)["version"] == 1
    assert _rows(store.read_base(doc.id)) == before and sorted(files.directory.iterdir()) == kept


def test_an_import_is_built_outside_the_stores_write_and_built_again_if_another_process_wrote(
    open_store, tmp_path
):
    """While an import builds, another document's writer commits at once (on SQLite too,
    whose writes take turns store-wide). An edit of the same document from another process
    meanwhile makes the import stale: it is built again inside a write, and the edit stands
    where the import does not say otherwise (an upsert after it)."""
    store, other = open_store(), open_store()  # two processes' stores
    files = SnapshotFiles(tmp_path / "snapshots")
    registry = Registry(store, files, 1 << 30)
    doc, neighbour = registry.create("d"), registry.create("n")
    doc.import_items([_batch([("a", (0.0, 0.0, 1.0, 1.0)), ("b", (2.0, 0.0, 3.0, 1.0))])])
    elsewhere = Registry(other, SnapshotFiles(tmp_path / "snapshots"), 1 << 30)[doc.id]
    build, builds = files.write, []

    def while_building(*args):
        builds.append(args[2])  # the version it builds
        if len(builds) == 1:
            writes = [
                lambda: neighbour.put(_batch([("n", (0, 0, 1, 1))])),
                lambda: elsewhere.put(_batch([("a", (5.0, 5.0, 6.0, 6.0))])),  # version 2, another process
                lambda: elsewhere.put(_batch([("c", (7.0, 7.0, 8.0, 8.0))])),  # version 3
            ]
            for write in writes:
                done: list = []
                writer = threading.Thread(target=lambda: done.append(write()), daemon=True)
                writer.start()
                writer.join(20)
                assert done, "a writer waited for an import's build"
        return build(*args)

    files.write = while_building
    assert doc.import_items([_batch([("b", (9.0, 9.0, 10.0, 10.0))])]) == (1, 4)
    assert builds == [2, 4]  # built as version 2, stale by then; built again as 4
    reopened = Registry(store, SnapshotFiles(tmp_path / "snapshots"), 1 << 30)[doc.id].snapshot
    for snap in (doc.snapshot, reopened):
        table = snap.document_table()
        shown = {table.item_id(p): tuple(table.read_boxes()[p]) for p in range(len(table))}
        assert shown == {"a": (5.0, 5.0, 6.0, 6.0), "b": (9.0, 9.0, 10.0, 10.0), "c": (7.0, 7.0, 8.0, 8.0)}
    assert store._rows("SELECT count(DISTINCT rowset) FROM bases WHERE doc_id = ?", doc.id)[0][0] == 1


def test_a_compaction_whose_file_cannot_be_written_stops_and_holds_no_index_in_memory(tmp_path, monkeypatch):
    """A disk refusing the new base's file (read-only) stops the compaction, where an import builds
    its base in memory: the whole index held at once (over 12 GB at 1e8 items). The
    document answers as before, its edits kept (folded by the next compaction), its staged
    rows and its partial file gone."""
    import app.documents
    import app.snapfile

    store = open_store(tmp_path)
    files = SnapshotFiles(tmp_path / "snapshots")
    doc = Registry(store, files, 1 << 30).create("d")
    doc.import_items([_batch([(f"i{k}", (k, 0.0, k + 1.0, 1.0)) for k in range(500)])])
    doc.put(_batch([("i3", (50.0, 50.0, 51.0, 51.0))]))
    doc.put(_batch([("new", (7.0, 7.0, 8.0, 8.0))]))
    before = doc.snapshot
    written = app.snapfile.write_base

    def full_disk(table, path, *args):
        path.write_bytes(b"partial")
        raise OSError(30, "Read-only file system")  # a full disk is refused: test_full_disk.py

    def in_memory(*args):
        raise AssertionError("the compaction built its base in memory")

    monkeypatch.setattr(app.snapfile, "write_base", full_disk)
    monkeypatch.setattr(app.documents, "build", in_memory)
    with pytest.raises(OSError, match="could not be written"):
        doc.compact()
    assert doc.snapshot is before and doc.snapshot.edits == 2
    assert sorted(p.name for p in files.directory.glob("*.vsnap")) == [f"{doc.id}.{before.base_id}.vsnap"]
    assert store._rows("SELECT count(DISTINCT rowset) FROM bases WHERE doc_id = ?", doc.id)[0][0] == 1
    monkeypatch.setattr(app.snapfile, "write_base", written)
    doc.compact()
    snap = doc.snapshot
    assert snap.edits == 0 and snap.base_id != before.base_id
    table = snap.document_table()
    assert tuple(table.read_boxes()[table.position("i3")]) == (50.0, 50.0, 51.0, 51.0)
    assert table.position("new") is not None and len(table) == 501


def test_an_import_whose_file_cannot_be_written_is_built_in_memory_only_if_small(tmp_path, monkeypatch):
    """A disk refusing the new base's file: an import of up to ``IN_MEMORY_ITEMS`` is built in
    memory and stored; a larger one is refused as the store's full disk is (507), storing
    nothing (its staged rows and partial file gone), where built in memory it would hold the
    whole index at once (over 12 GB at 1e8 items)."""
    import app.documents
    import app.snapfile
    import app.snapshots
    from app.errors import StorageFull

    store = open_store(tmp_path)
    files = SnapshotFiles(tmp_path / "snapshots")
    doc = Registry(store, files, 1 << 30).create("d")
    doc.import_items([_batch([("a", (1.0, 1.0, 2.0, 2.0))])])
    before, built = doc.snapshot, []

    def full_disk(table, path, *args):
        path.write_bytes(b"partial")
        raise OSError(30, "Read-only file system")  # a full disk is refused: test_full_disk.py

    def in_memory(table, *args):
        built.append(len(table))
        return app.snapshots.build(table, *args)

    monkeypatch.setattr(app.snapfile, "write_base", full_disk)
    monkeypatch.setattr(app.documents, "build", in_memory)
    monkeypatch.setattr(app.documents, "IN_MEMORY_ITEMS", 100)
    with pytest.raises(StorageFull, match="more than an import builds in memory"):
        doc.import_items([_batch([(f"i{k}", (k, 0.0, k + 1.0, 1.0)) for k in range(100)])])
    assert built == [] and doc.snapshot is before and store.document(doc.id)["version"] == before.version
    assert sorted(p.name for p in files.directory.iterdir()) == [f"{doc.id}.{before.base_id}.vsnap"]
    assert store._rows("SELECT count(DISTINCT rowset) FROM bases WHERE doc_id = ?", doc.id)[0][0] == 1
    assert doc.import_items([_batch([(f"i{k}", (k, 0.0, k + 1.0, 1.0)) for k in range(99)])]) == (99, 2)
    assert built == [100]  # "a" and the 99: built in memory, and shown
    table = doc.snapshot.document_table()
    assert len(table) == 100 and tuple(table.read_boxes()[table.position("i98")]) == (98.0, 0.0, 99.0, 1.0)


def test_edits_are_saved_beside_the_base_as_they_come_and_an_open_takes_them_from_there(
    tmp_path, monkeypatch
):
    """Every ``SAVE_EDITS_EVERY`` edits, they are saved beside the base's file in the
    background; the next open takes them from it and replays from the store only those
    made since; a server that stops saves those not saved yet. A compaction's new base leaves
    the old base's saved edits behind: removed with its file. A file of no current base is
    swept."""
    import app.documents
    import app.snapshots

    monkeypatch.setattr(app.documents, "SAVE_EDITS_EVERY", 5)
    store = open_store(tmp_path)
    files = SnapshotFiles(tmp_path / "snapshots")
    doc = Registry(store, files, 1 << 30).create("d")
    doc.import_items([_batch([(f"i{k}", (k, 0.0, k + 1.0, 1.0)) for k in range(300)])])
    base_id = doc.snapshot.base_id
    path = files.edits_path(doc.id, base_id)
    for k in range(7):
        doc.put(_batch([(f"i{k}", (k, 5.0, k + 1.0, 6.0))]))
        _saved(doc)
    assert editfile.saved_version(path) == doc.snapshot.version - 2  # saved at the 5th edit, not since
    replayed: list[int] = []
    with_edits = app.snapshots.Snapshot.with_edits

    def counted(snap, edits):
        edits = list(edits)
        replayed.append(len(edits))
        return with_edits(snap, edits)

    monkeypatch.setattr(app.snapshots.Snapshot, "with_edits", counted)
    registry = Registry(store, files, 1 << 30)
    reopened = registry[doc.id]
    assert replayed == [2] and reopened.edits_saved == (base_id, 5)  # the 6th and 7th from the store
    assert [reopened.snapshot.tree.get(reopened.snapshot.position(f"i{k}")) for k in range(8)] == [
        *((k, 5.0, k + 1.0, 6.0) for k in range(7)),
        (7.0, 0.0, 8.0, 1.0),
    ]
    asyncio.run(registry.settle())  # as a server stops: what is not saved yet is
    assert editfile.saved_version(path) == doc.snapshot.version
    assert Registry(store, files, 1 << 30)[doc.id].edits_saved == (base_id, 7) and replayed == [2]
    monkeypatch.undo()
    reopened.compact()
    assert not path.exists() and reopened.snapshot.base_id != base_id
    path.write_bytes(b"left by a process killed mid-compaction")
    assert files.sweep(store, grace=0) == 1 and not path.exists()
    store.close()


def test_edits_saved_by_their_age_wait_longer_when_a_save_costs_more(tmp_path):
    """A save by age comes ``VANTAGE_SAVE_EDITS_SECONDS`` after the first edit not saved, or
    20 times as long as the last save took if longer: saves of many edits pending (seconds
    each at 1e8) take a small share of a core however often edits come."""
    import time

    store = open_store(tmp_path)
    try:
        doc = Registry(store, SnapshotFiles(tmp_path / "snapshots"), 1 << 30).create("d")
        doc.import_items([_batch([(f"i{k}", (k, 0.0, k + 1.0, 1.0)) for k in range(50)])])
        path = doc.files.edits_path(doc.id, doc.snapshot.base_id)
        doc.put(_batch([("i1", (1.0, 5.0, 2.0, 6.0))]))
        doc._save_took = 10.0  # as if the last save took 10 s: the next by age waits 200 s
        doc._unsaved_since = time.monotonic() - 100
        assert doc.save_edits_older_than(1.0) is None and not path.exists()
        doc._unsaved_since = time.monotonic() - 201
        doc.save_edits_older_than(1.0).join()
        assert editfile.saved_version(path) == doc.snapshot.version
        assert doc.save_edits_older_than(0.0) is None  # none left to save
    finally:
        store.close()


def _saved(doc) -> None:
    """Wait for ``doc``'s edits being saved, if they are."""
    for thread in threading.enumerate():
        if thread.name == f"save edits of {doc.id}":
            thread.join()


def test_edits_up_to_the_compaction_never_rebuild_the_documents_tree(tmp_path):
    """A tree rebuilds itself once its buffered edits pass 256 + n/512; a document's must not,
    before the document folds its edits into a new base in the background (in an edit, at
    1e8 items, it took a minute and GBs). So every edit up to the compaction leaves the tree
    on its base's arrays (the mapped file's), with every answer still exact."""
    store = open_store(tmp_path)
    doc = Registry(store, SnapshotFiles(tmp_path / "snapshots"), 1 << 30).create("d")
    n, rng = 20_000, np.random.default_rng(3)
    xy = rng.uniform(0, 1000, (n, 2))
    doc.import_items([_batch([(f"i{k}", (x, y, x + 2, y + 2)) for k, (x, y) in enumerate(xy.tolist())])])
    built = doc.snapshot.tree._boxes
    moved = {f"i{k}": tuple(rng.uniform(0, 1000, 2).tolist()) for k in range(1000)}  # > 256 + n/512
    items = [(i, (x, y, x + 1, y + 1)) for i, (x, y) in moved.items()]
    for start in range(0, len(items), 250):
        batch = _batch(items[start : start + 250])
        doc.edit(list(zip(batch.ids, map(tuple, batch.boxes.tolist()), batch.bodies, strict=True)))
    assert not doc.needs_compaction()
    snap = doc.snapshot
    assert snap.tree._boxes is built, "an edit rebuilt the tree before the document's compaction"
    boxes = np.column_stack([xy, xy + 2])
    for item_id, (x, y) in moved.items():
        boxes[int(item_id[1:])] = (x, y, x + 1, y + 1)
    for rect in ((0, 0, 300, 300), (250, 400, 900, 1000)):
        got = {snap.item_id(p) for p in snap.tree.query(rect).tolist()}
        assert got == {f"i{k}" for k in oracle.query(boxes, np.arange(n), rect)}
    store.close()


def test_an_edit_costs_the_same_however_many_edits_are_pending(monkeypatch):
    """What edits changed since the base is kept in persistent maps (the snapshot's and the
    overview's) and in the tree's insert buffer (rows only added, shared by copies), each
    shared by an edit's snapshot with the one before: one more edit allocates as much with
    30,000 edits pending as with 1,000, where copying them (dicts, the buffer's arrays) cost
    O(edits), ~180 ms an edit with the 392k a 1e8-item document piles up before its compaction."""
    import tracemalloc

    import spatial.overview._edits
    from app.snapshots import build

    # The overview folds its recent edits at the service's threshold, as a document's do, not
    # every 5 (tests/conftest.py): 6,000 folds of up to 30,000 edits took ~25 s here
    monkeypatch.setattr(spatial.overview._edits, "FOLD_AFTER", 2048)
    n, rng = 20_000, np.random.default_rng(5)
    xy = rng.uniform(0, 1000, (n, 2))
    table = ItemTable.of([f"i{k}" for k in range(n)], np.column_stack([xy, xy + 2]), [b"{}"] * n)
    snap = build(table, 1, "b")
    snap.tree.max_buffered = 10**6  # no rebuild in between: what is measured is the buffer's growth
    mine = tuple(
        tracemalloc.Filter(True, f"*/{name}")
        for name in ("app/snapshots.py", "spatial/overview/*.py", "spatial/quadtree.py")
    )

    def one_more(snap) -> int:
        """Bytes one more edit's snapshot holds, allocated in those files: the least of three
        (the shared change log's list grows now and then, amortized)."""
        sizes = []
        for _ in range(3):
            tracemalloc.start()
            kept = snap.with_edits([("i7", snap.version + 1, (5.0, 5.0, 9.0, 9.0), b"{}")])  # noqa: F841 (held)
            traces = tracemalloc.take_snapshot().filter_traces(mine)
            tracemalloc.stop()
            sizes.append(sum(s.size for s in traces.statistics("filename")))
        return min(sizes)

    costs = []
    for pending in (1_000, 30_000):
        moves = rng.integers(0, n, pending - snap.edits)
        edits = [
            (f"i{k}", snap.version + 1 + e, (float(k % 900), 1.0, k % 900 + 3.0, 4.0), b"{}")
            for e, k in enumerate(moves.tolist())
        ]
        snap, _ = snap.with_edits(edits)
        assert snap.edits == pending
        costs.append(one_more(snap))
    assert costs[1] < 3 * costs[0], (
        f"one more edit allocated {costs[1]} B with 30,000 pending, {costs[0]} B with 1,000"
    )


def test_the_log_clients_catch_up_from_keeps_to_its_limit_even_for_edits_taken_at_once(monkeypatch):
    """Edits applied at once (an open catching up on thousands) whose entries alone pass the
    log's limit are not kept: a client from before them starts over, one after them catches up.
    Kept, 40,000 moves at 1e8 items held 1.16M entries, and an open rebuilt them all."""
    import app.snapshots
    from app.snapshots import build

    monkeypatch.setattr(app.snapshots, "LOG_LIMIT", 50)
    n = 200
    table = ItemTable.of(
        [f"i{k}" for k in range(n)], np.array([[k, 0, k + 1, 1] for k in range(n)], float), [b"{}"] * n
    )
    snap = build(table, 1, "b")
    snap, _ = snap.with_edits([("i3", 2, (3.0, 5.0, 4.0, 6.0), b"{}")])
    assert "i3" in snap.edited_since(1)
    many = [(f"i{k}", 3 + k, (k + 0.5, 7.0, k + 1.0, 8.0), b"{}") for k in range(60)]
    after, changed = snap.with_edits(many)
    assert len(changed) > 50 and len(after.log) <= 50
    assert after.edited_since(snap.version) is None  # from before them: start over
    assert after.edited_since(after.version) == []
    last, _ = after.with_edits([("i100", after.version + 1, (0.0, 9.0, 1.0, 10.0), b"{}")])
    assert "i100" in last.edited_since(after.version)


def test_a_small_documents_build_makes_its_scratch_in_memory_not_in_files(tmp_path, monkeypatch):
    """An import's scratch arrays under ``SCRATCH_IN_MEMORY`` are made in memory: a small
    document's base took 48 files of a few bytes (each a fraction of a millisecond, ~150 in a
    compaction), its bodies' and ids' spills left; a large array still goes to a file."""
    import app.packed

    opened: list[int] = []
    temporary = tempfile.TemporaryFile
    monkeypatch.setattr(
        app.packed.tempfile, "TemporaryFile", lambda **kw: opened.append(1) or temporary(**kw)
    )
    store = open_store(tmp_path)
    try:
        doc = Registry(store, SnapshotFiles(tmp_path / "snapshots"), 1 << 30).create("d")
        boxes = np.tile(np.random.default_rng(1).uniform(0, 1000, (300, 2)), 2)  # points
        doc.import_items([_batch([(f"i{k}", tuple(b)) for k, b in enumerate(boxes.tolist())])])
        assert len(opened) <= 16, f"{len(opened)} scratch files for 300 items"
        assert mapping(app.packed.scratch_array(tmp_path, app.packed.SCRATCH_IN_MEMORY, np.uint8)) is not None
    finally:
        store.close()
