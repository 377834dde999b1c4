"""The store interface, run on both engines (SQLite, and a real PostgreSQL server): documents,
bases and edits as written, all or nothing, gap-free versions under concurrent writers from
two processes' stores, and a change log that a follower reads in commit order."""

import threading
import time

import numpy as np
import pytest
import zstandard
from service import item_json

import app.stores.base
import app.stores.sqlite
from app.errors import Conflict, NotFound
from app.stores import open_store as opened
from app.stores.postgres import POLL_SECONDS
from app.stores.sqlite import SQLiteStore
from app.table import ItemTable, Packed


def _table(n: int, seed: int = 0, prefix: str = "i") -> ItemTable:
    rng = np.random.default_rng(seed)
    boxes = rng.uniform(-1e6, 1e6, (n, 4))
    boxes[:, 2:] = boxes[:, :2] + rng.uniform(0, 100, (n, 2))
    ids = [f"{prefix}{k}" for k in range(n)]
    return ItemTable.of(
        ids, boxes, [item_json(i, b, n=k) for k, (i, b) in enumerate(zip(ids, boxes, strict=True))]
    )


def _rows(table: ItemTable) -> dict[str, tuple]:
    return {table.item_id(p): (tuple(table.boxes[p]), bytes(table.bodies[p])) for p in range(len(table))}


def test_documents_are_created_listed_found_and_deleted(open_store):
    store = open_store()
    a, b = store.create_document("a"), store.create_document("b")
    assert (a["name"], a["version"], a["items"], a["bounds"], a["base_id"]) == ("a", 0, 0, None, None)
    assert [d["id"] for d in store.documents()] == [a["id"], b["id"]]  # oldest first
    assert store.document(b["id"]) == b
    store.delete_document(a["id"])
    assert [d["id"] for d in store.documents()] == [b["id"]]
    with pytest.raises(NotFound, match=a["id"]):
        store.document(a["id"])
    with pytest.raises(NotFound, match="nope"):
        store.delete_document("nope")
    with pytest.raises(Conflict, match="VANTAGE_MAX_DOCUMENTS"):
        store.create_document("c", max_documents=1)


def test_a_base_of_many_chunks_reads_back_as_written(open_store, monkeypatch):
    monkeypatch.setattr(app.stores.base, "CHUNK", 1000)  # 5 chunks and a part
    store = open_store()
    doc = store.create_document("d")["id"]
    table = _table(5500)
    assert store.write_items(doc, table) == 1
    back = store.read_base(doc)
    assert _rows(back) == _rows(table) and len(back) == 5500
    meta = store.document(doc)
    assert (meta["version"], meta["base_version"], meta["items"]) == (1, 1, 5500)
    b = table.boxes
    assert meta["bounds"] == [b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max()]
    assert len(store.read_base(store.create_document("empty")["id"])) == 0


def test_a_base_is_cut_into_rows_by_bytes_too(open_store, monkeypatch):
    monkeypatch.setattr(app.stores.base, "CHUNK_BYTES", 4000)  # ~180 small bodies a row
    store = open_store()
    doc = store.create_document("d")["id"]
    box = [0.0, 0.0, 1.0, 1.0]
    big = ItemTable.of(["big"], np.array([box]), [item_json("big", box, t="x" * 9000)])
    table = ItemTable.merge([_table(1000), big])  # one body alone over the limit: a row of its own
    rows = list(app.stores.base.chunks(table))
    assert len(rows) >= 6 and all(len(r[3]) <= 4000 or len(np.frombuffer(r[4], np.int64)) == 2 for r in rows)
    store.write_items(doc, table)
    assert _rows(store.read_base(doc)) == _rows(table)


def test_a_table_whose_ids_end_in_int32_as_a_file_keeps_them_is_stored_alike(open_store):
    store = open_store()
    doc = store.create_document("d")["id"]
    table = _table(700)
    narrow = ItemTable(
        Packed(table.ids.buffer, table.ids.offsets.astype(np.int32)), table.bodies, table.boxes
    )
    store.write_items(doc, narrow)
    assert _rows(store.read_base(doc)) == _rows(table)


def test_edits_keep_the_last_of_each_item_and_an_import_folds_them(open_store):
    store = open_store()
    doc = store.create_document("d")["id"]
    store.write_items(doc, _table(10))
    with store.writing(doc) as write:
        v2 = write.bump()
        write.write_edits(
            v2, [("i1", (0, 0, 1, 1), b'{"id":"i1"}'), ("new", (5, 5, 6, 6), b'{"id":"new"}')], 11, None
        )
    with store.writing(doc) as write:
        v3 = write.bump()
        write.write_edits(v3, [("i1", (2, 2, 3, 3), b'{"id":"i1","v":3}'), ("i2", None, None)], 10, None)
    assert (v2, v3) == (2, 3)
    assert store.edits(doc) == [
        ("new", 2, (5, 5, 6, 6), b'{"id":"new"}'),
        ("i1", 3, (2, 2, 3, 3), b'{"id":"i1","v":3}'),
        ("i2", 3, None, None),
    ]
    assert [e[0] for e in store.edits(doc, after=2)] == ["i1", "i2"]
    items = _rows(store.read_items(doc))
    assert set(items) == {f"i{k}" for k in range(10)} - {"i2"} | {"new"}
    assert items["i1"] == ((2, 2, 3, 3), b'{"id":"i1","v":3}')
    store.write_items(doc, _table(3))
    assert store.edits(doc) == [] and len(store.read_items(doc)) == 3


def test_a_write_that_fails_leaves_nothing(open_store):
    store = open_store()
    doc = store.create_document("d")["id"]
    store.write_items(doc, _table(50))
    head = store.log_head()
    with pytest.raises(RuntimeError, match="midway"), store.writing(doc) as write:
        version = write.bump()
        write.write_base(_table(80, seed=1, prefix="x"), version, "b", None)
        raise RuntimeError("midway")
    assert store.document(doc)["version"] == 1 and _rows(store.read_items(doc)) == _rows(_table(50))
    assert store.log_head() == head


def test_the_change_log_has_a_row_for_each_write_from_the_last_import(open_store):
    store = open_store()
    doc, other = store.create_document("d")["id"], store.create_document("o")["id"]
    store.write_items(doc, _table(5))
    for k in range(3):
        with store.writing(doc) as write:
            write.write_edits(write.bump(), [(f"e{k}", (0, 0, 1, 1), b"{}")], 6 + k, None)
    store.write_items(other, _table(2))
    log = store.log_after(0)
    assert [(c.doc_id, c.version, c.kind) for c in log] == [
        (doc, 1, "import"),
        (doc, 2, "edit"),
        (doc, 3, "edit"),
        (doc, 4, "edit"),
        (other, 1, "import"),
    ]
    assert [c.seq for c in log] == sorted(c.seq for c in log) and store.log_head() == log[-1].seq
    assert store.log_after(log[2].seq) == log[3:]
    store.write_items(doc, _table(5))  # the log reaches back to the base, no further
    assert [(c.doc_id, c.version) for c in store.log_after(0)] == [(other, 1), (doc, 5)]
    store.delete_document(doc)  # a deletion is logged, so followers learn of it
    last = store.log_after(0)[-1]
    assert (last.doc_id, last.version, last.kind) == (doc, 5, "delete")


def test_writers_in_two_processes_take_turns_and_lose_nothing(open_store):
    """Two stores on the same data stand for two processes (workers, or replicas): their
    concurrent writers of one document get gap-free versions, and every edit is kept."""
    stores = [open_store(), open_store()]
    doc = stores[0].create_document("d")["id"]
    errors = []

    def writer(store, name: str) -> None:
        try:
            for k in range(15):
                with store.writing(doc) as write:
                    meta_version = write.meta["version"]
                    version = write.bump()
                    assert version == meta_version + 1  # the row was locked when read
                    time.sleep(0.001)  # widen the window a lost update would need
                    write.write_edits(version, [(f"{name}{k}", (k, k, k + 1, k + 1), b"{}")], 0, None)
        except Exception as error:  # pragma: no cover - reported below
            errors.append(error)

    threads = [threading.Thread(target=writer, args=(s, n)) for s, n in zip(stores, "ab", strict=True)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert stores[1].document(doc)["version"] == 30
    assert sorted(v for _, v, _, _ in stores[1].edits(doc)) == list(range(1, 31))
    assert {e[0] for e in stores[0].edits(doc)} == {f"{n}{k}" for n in "ab" for k in range(15)}
    assert [c.version for c in stores[0].log_after(0)] == list(range(1, 31))  # commit order


def test_a_write_by_another_process_is_noticed_at_once(open_store, monkeypatch):
    """Without the safety poll (PostgreSQL's, pushed out of reach here), so what notices a
    write is the engine's own signal: SQLite's data_version, PostgreSQL's NOTIFY."""
    import app.stores.postgres

    monkeypatch.setattr(app.stores.postgres, "POLL_SECONDS", 3600.0)
    watcher, writer = open_store(), open_store()
    doc = writer.create_document("d")["id"]
    time.sleep(0.3)  # the listener is connected, and has said so
    while watcher.changed():
        pass
    woken = []
    watcher.on_change = lambda: woken.append(time.monotonic())
    writer.write_items(doc, _table(3))
    committed = time.monotonic()
    while not watcher.changed():
        assert time.monotonic() < committed + 0.5, "a committed write was not noticed within 0.5 s"
        time.sleep(0.005)
    assert [(c.doc_id, c.kind) for c in watcher.log_after(0)] == [(doc, "import")]
    if watcher.engine == "postgresql":  # the follower is woken too, not left to its next look
        assert woken and woken[0] - committed < 0.5


WRITES = 40


def test_a_follower_of_the_log_misses_no_write(open_store):
    """Writers of several documents commit in some order while a follower reads the log from
    the last row it saw: it must see every row, so no row may commit after a later one is seen.
    Each writer pauses between appending its row and committing, where a reorder would hide."""
    stores = [open_store() for _ in range(4)]
    docs = [stores[0].create_document(f"d{k}")["id"] for k in range(4)]
    seen: list = []
    done = threading.Event()

    def follow() -> None:
        cursor = 0
        while not done.is_set() or stores[0].log_after(cursor):
            for change in stores[0].log_after(cursor):
                seen.append(change)
                cursor = change.seq

    def write(store, doc) -> None:
        for k in range(WRITES):
            with store.writing(doc) as write:
                write.write_edits(write.bump(), [(f"e{k}", (0, 0, 1, 1), b"{}")], k + 1, None)
                time.sleep(0.001 * (k % 4))  # appended, not yet committed

    follower = threading.Thread(target=follow)
    follower.start()
    writers = [threading.Thread(target=write, args=(s, d)) for s, d in zip(stores, docs, strict=True)]
    for t in writers:
        t.start()
    for t in writers:
        t.join()
    done.set()
    follower.join()
    assert len(seen) == len(stores[0].log_after(0)) == 4 * WRITES


def test_a_missed_notify_only_delays_a_write_s_notice_on_postgresql(database_url, tmp_path):
    """NOTIFY can be lost (a listener reconnecting, say): the safety poll notices the write
    within its period all the same."""

    class Deaf(threading.Event):  # every notification lost
        def set(self) -> None:
            pass

    watcher, writer = opened(tmp_path / "w", database_url), opened(tmp_path / "r", database_url)
    try:
        watcher._woken = Deaf()
        doc = writer.create_document("d")["id"]
        while watcher.changed():
            pass
        writer.write_items(doc, _table(3))
        deadline = time.monotonic() + 3 * POLL_SECONDS
        while not watcher.changed():
            assert time.monotonic() < deadline, "a write went unnoticed past the safety poll's period"
            time.sleep(0.02)
        assert [c.doc_id for c in watcher.log_after(0)][-1] == doc
    finally:
        watcher.close()
        writer.close()


def test_a_base_is_stored_compressed_with_each_box_once_and_earlier_versions_rows_read_back(open_store):
    store = open_store()
    table = _table(3000)
    doc, raw, zstd = (store.create_document(name)["id"] for name in ("d", "raw", "zstd"))
    store.write_items(doc, table)
    ((codec, stored, boxes),) = store._rows(
        "SELECT codec, length(bodies), length(boxes) FROM bases WHERE doc_id = ?", doc
    )
    # each box is read back from its item's JSON: not kept a second time
    assert codec == app.stores.base.LEAN and stored < len(table.bodies.buffer) / 2 and boxes == 0
    base = app.stores.base
    pack = zstandard.ZstdCompressor().compress
    (row,) = base.chunks(table)  # 3000 items: one row, and the boxes earlier versions stored
    k, i, io, b, bo, x = *row, table.boxes.tobytes()
    with store.writing(raw) as write:  # rows as a store before format 5 (SQLite) or 2 held them
        write._write_base_rows(iter([(raw, 0, k, i, io, b, bo, x, base.RAW)]))
    with store.writing(zstd) as write:  # rows whose boxes were stored too
        rest = pack(i), pack(base._lengths(io)), pack(b), pack(base._lengths(bo)), pack(x)
        write._write_base_rows(iter([(zstd, 0, k, *rest, base.ZSTD)]))
    assert (
        _rows(store.read_base(doc))
        == _rows(store.read_base(raw))
        == _rows(store.read_base(zstd))
        == _rows(table)
    )


def test_a_base_row_whose_items_hold_no_box_is_refused_clearly(open_store):
    store = open_store()
    doc = store.create_document("d")["id"]
    store.write_items(doc, ItemTable.of(["a"], np.zeros((1, 4)), [b'{"id":"a"}']))
    with pytest.raises(app.stores.base.StoreError, match=r"items cannot be read.*x0"):
        store.read_base(doc)


# The two tables that format 6 changed, as formats 4 and 5 laid them out (format 4: no codec)
SQLITE_FORMAT_5 = """
CREATE TABLE documents (
    id TEXT PRIMARY KEY, name TEXT NOT NULL, created REAL NOT NULL,
    version INTEGER NOT NULL DEFAULT 0, base_id TEXT, base_version INTEGER NOT NULL DEFAULT 0,
    items INTEGER NOT NULL DEFAULT 0, bounds TEXT
);
CREATE TABLE bases (
    doc_id TEXT NOT NULL REFERENCES documents(id) ON DELETE CASCADE,
    chunk INTEGER NOT NULL,
    ids BLOB NOT NULL, id_offsets BLOB NOT NULL,
    bodies BLOB NOT NULL, body_offsets BLOB NOT NULL,
    boxes BLOB NOT NULL,
    codec INTEGER NOT NULL DEFAULT 0,
    PRIMARY KEY (doc_id, chunk)
) WITHOUT ROWID;
"""


@pytest.mark.parametrize("format", [4, 5])
def test_an_earlier_sqlite_store_is_migrated_its_rows_read_back_and_compacted(tmp_path, format):
    import sqlite3

    from app.stores import sqlite as engine

    table = _table(500)
    db = sqlite3.connect(tmp_path / "vantage.sqlite3")
    layout = (
        SQLITE_FORMAT_5 if format == 5 else SQLITE_FORMAT_5.replace("codec INTEGER NOT NULL DEFAULT 0,", "")
    )
    db.executescript(layout + engine.SCHEMA)  # the tables format 6 has that these lack: as they were
    db.execute(f"PRAGMA user_version = {format}")
    db.execute(
        "INSERT INTO documents (id, name, created, version, base_version, items) VALUES ('d', 'd', 0, 1, 1, 500)"
    )
    (row,) = app.stores.base.chunks(table)  # 500 items: one row
    if format == 4:  # raw blobs, the boxes too
        db.execute("INSERT INTO bases VALUES ('d', ?, ?, ?, ?, ?, ?)", (*row, table.boxes.tobytes()))
    else:
        encoded = app.stores.base.encoded(row, app.stores.base.packer())
        db.execute("INSERT INTO bases VALUES ('d', ?, ?, ?, ?, ?, ?, ?)", encoded)
    db.commit()
    db.close()
    store = opened(tmp_path)
    try:
        assert _rows(store.read_base("d")) == _rows(table)
        _compact(store, "d", _table(30, prefix="k"))  # a new rowset beside the migrated one
        assert _rows(store.read_base("d")) == _rows(_table(30, prefix="k"))
        store.write_items("d", _table(20, prefix="j"))  # written compressed beside the old ones
        assert len(store.read_base("d")) == 20
    finally:
        store.close()


def test_a_postgresql_store_of_format_1_is_migrated(database_url):
    import psycopg

    from app.stores.postgres import PostgresStore

    table = _table(500)
    store = PostgresStore(database_url)
    doc = store.create_document("d")["id"]
    store.close()
    with psycopg.connect(database_url, autocommit=True) as db:  # as format 1 laid it out
        db.execute("ALTER TABLE bases DROP COLUMN codec, DROP COLUMN rowset, ADD PRIMARY KEY (doc_id, chunk)")
        db.execute("ALTER TABLE documents DROP COLUMN rowset")
        db.execute("UPDATE vantage_format SET format = 1")
    store = PostgresStore(database_url)
    try:
        store.write_items(doc, table)
        assert _rows(store.read_base(doc)) == _rows(table)
        _compact(store, doc, _table(30, prefix="k"))
        assert _rows(store.read_base(doc)) == _rows(_table(30, prefix="k"))
    finally:
        store.close()


def _compact(store, doc: str, table: ItemTable) -> None:
    """``table`` made the base of ``doc`` as a compaction makes it: staged, pointed at, the old
    rows dropped."""
    staged = store.stage_base(doc, table)
    with store.writing(doc) as write:
        old = write.compact_base(staged, write.meta["version"], "b")
    store.drop_rows(doc, old)


def _rowsets(store, doc: str) -> dict[int, int]:
    """Each rowset of ``doc`` in the store, and how many rows it has."""
    return dict(store._rows("SELECT rowset, count(*) FROM bases WHERE doc_id = ? GROUP BY rowset", doc))


def test_a_compactions_rows_are_staged_unseen_while_writers_go_on_then_swapped_in_one_write(
    open_store, monkeypatch
):
    """A compaction's rows are written a short transaction a row, locking no document: a
    writer of the same document commits between two of them. Until the document is pointed
    at them no read sees them; then every read does, and the old base's rows go."""
    monkeypatch.setattr(app.stores.base, "CHUNK", 100)
    store = open_store()
    doc = store.create_document("d")["id"]
    old, new = _table(250, prefix="a"), _table(350, prefix="b")
    store.write_items(doc, old)
    (old_rowset,) = _rowsets(store, doc)
    encode, second, resume = app.stores.base.encoded, threading.Event(), threading.Event()

    def pausing(row, pack):  # the staging waits before its second row, its first committed
        if row[0] == 1:
            second.set()
            assert resume.wait(20)
        return encode(row, pack)

    monkeypatch.setattr(app.stores.base, "encoded", pausing)
    staged: list = []
    stager = threading.Thread(target=lambda: staged.append(store.stage_base(doc, new)))
    stager.start()
    try:
        assert second.wait(20)
        edited = threading.Thread(target=_edit_one, args=(store, doc))
        edited.start()
        edited.join(20)
        assert not edited.is_alive(), "a writer of the document waited for the staging"
        assert _rows(store.read_base(doc)) == _rows(old)  # a staged row is no read's
    finally:
        resume.set()
        stager.join(20)
    (staged,) = staged
    assert staged.rows == 4 and _rowsets(store, doc) == {old_rowset: 3, staged.rowset: 4}
    assert _rows(store.read_base(doc)) == _rows(old)
    with store.writing(doc) as write:
        assert write.compact_base(staged, 2, "b") == old_rowset
    assert _rows(store.read_base(doc)) == _rows(new)
    assert [e[0] for e in store.edits(doc)] == []  # the edit at 2, folded
    assert store.drop_rows(doc, old_rowset) == 3 and _rowsets(store, doc) == {staged.rowset: 4}
    assert store.drop_rows(doc, staged.rowset) == 0  # the base's rows are never dropped


def _edit_one(store, doc: str) -> None:
    with store.writing(doc) as write:
        write.write_edits(
            write.bump(), [("a0", (0.0, 0.0, 1.0, 1.0), item_json("a0", (0, 0, 1, 1)))], 250, None
        )


def test_a_staging_that_fails_leaves_no_rows_and_a_swept_one_cannot_be_swapped_in(open_store, monkeypatch):
    monkeypatch.setattr(app.stores.base, "CHUNK", 100)
    store = open_store()
    doc = store.create_document("d")["id"]
    store.write_items(doc, _table(150))
    before = _rowsets(store, doc)
    encode = app.stores.base.encoded

    def failing(row, pack):
        if row[0] == 2:
            raise OSError("disk gone")
        return encode(row, pack)

    monkeypatch.setattr(app.stores.base, "encoded", failing)
    with pytest.raises(OSError, match="disk gone"):
        store.stage_base(doc, _table(300, prefix="b"))
    assert _rowsets(store, doc) == before  # its two rows written went again
    monkeypatch.setattr(app.stores.base, "encoded", encode)
    staged = store.stage_base(doc, _table(300, prefix="b"))
    assert store.sweep_rows() == 0  # staged within the grace: a compaction's under way, maybe
    with store._unlocked(doc) as write:  # a sweep cut short after its first row
        write._sql(app.stores.base.DROP_ROW, doc, staged.rowset, doc, doc, staged.rowset)
    with store.writing(doc) as write, pytest.raises(app.stores.base.StoreError, match="1 of the 3 staged"):
        write.compact_base(staged, 1, "b")
    time.sleep(0.01)
    assert store.sweep_rows(grace=0) == 2  # left by a compaction killed, say: gone, the base's kept
    assert _rowsets(store, doc) == before
    with store.writing(doc) as write, pytest.raises(app.stores.base.StoreError, match="3 of the 3 staged"):
        write.compact_base(staged, 1, "b")
    assert _rows(store.read_base(doc)) == _rows(_table(150)) and store.document(doc)["base_id"] is None


def _incompressible(n: int, seed: int, prefix: str = "n") -> ItemTable:
    """``n`` items whose bodies zstd halves at best (random hex): ~5 MB of rows at 12,000."""
    rng = np.random.default_rng(seed)
    bodies = [rng.bytes(400).hex().encode() for _ in range(n)]
    return ItemTable.of([f"{prefix}{k}" for k in range(n)], _table(n).boxes, bodies)


def test_no_commit_copies_the_wal_into_the_database_the_checkpointer_does(tmp_path, monkeypatch):
    """SQLite's autocheckpoint made whichever commit crossed 1000 pages copy the WAL, another
    process's staged rows and all: an edit waited for that copy and its fsync. With the
    checkpointer (and the staging's own copies) paused, neither the rows' commits nor another
    store's edit copies anything into the database file; the checkpointer then does, and the
    WAL is cut back to its limit when it starts over (at once after a write of a whole base in
    one transaction)."""
    monkeypatch.setattr(app.stores.sqlite, "WAL_LIMIT_BYTES", 1 << 20)
    copy, checkpoint = app.stores.sqlite._Checkpointer.copy, SQLiteStore.checkpoint
    monkeypatch.setattr(app.stores.sqlite._Checkpointer, "copy", lambda self: None)
    monkeypatch.setattr(SQLiteStore, "checkpoint", lambda self: None)  # nor the staging's own
    store, other = SQLiteStore(tmp_path), SQLiteStore(tmp_path)  # two processes' stores
    try:
        doc = store.create_document("d")["id"]
        other.write_items(other.create_document("o")["id"], _table(10, prefix="a"))
        database, wal = tmp_path / "vantage.sqlite3", tmp_path / "vantage.sqlite3-wal"
        size = database.stat().st_size
        store.stage_base(doc, _incompressible(12_000, seed=3))  # ~5 MB of rows: 1,200 pages
        _edit_one(other, other.documents()[1]["id"])
        assert database.stat().st_size == size, "a commit copied the WAL into the database"
        assert wal.stat().st_size > 4 << 20
        monkeypatch.setattr(app.stores.sqlite._Checkpointer, "copy", copy)
        monkeypatch.setattr(SQLiteStore, "checkpoint", checkpoint)
        other._checkpointer.poke()
        deadline = time.monotonic() + 20
        while database.stat().st_size <= size + (4 << 20) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert database.stat().st_size > size + (4 << 20), "the checkpointer copied nothing"
        while wal.stat().st_size > 1 << 20 and time.monotonic() < deadline:
            _edit_one(other, other.documents()[1]["id"])  # once all is copied the WAL starts over,
            time.sleep(0.05)  # cut back to its limit
        assert wal.stat().st_size <= 1 << 20, "the WAL kept its size"
        other.write_items(doc, _incompressible(12_000, seed=5, prefix="m"))
        assert wal.stat().st_size <= 1 << 20, "a write of the whole base left the WAL past its limit"
    finally:
        store.close()
        other.close()


def test_dropping_a_rowset_does_not_write_its_pages_again(tmp_path, monkeypatch):
    """SQLite built with SECURE_DELETE zeroes each page it frees: dropping an old base's rows
    wrote all of them to the WAL again (~400 MB after a 10M board's compaction), which the
    writers then waited for. The WAL grows by a few pages a row instead."""
    monkeypatch.setattr(app.stores.sqlite._Checkpointer, "copy", lambda self: None)
    monkeypatch.setattr(SQLiteStore, "checkpoint", lambda self: None)
    store = SQLiteStore(tmp_path)
    try:
        doc = store.create_document("d")["id"]
        staged = store.stage_base(doc, _incompressible(12_000, seed=4))
        wal = tmp_path / "vantage.sqlite3-wal"
        before = wal.stat().st_size
        assert store.drop_rows(doc, staged.rowset) == staged.rows
        assert wal.stat().st_size - before < 1 << 20, "the dropped rows' pages were written again"
    finally:
        store.close()
