"""Crash safety: the real server killed with SIGKILL in the middle of an import and of a burst
of edits, then restarted: every committed version intact, nothing of the interrupted one. And
the edits saved beside a base (``editfile``), a cache a restart takes them from: saved when
they should be, never taken for edits they do not hold."""

import contextlib
import logging
import os
import signal
import sqlite3
import threading
import time

import httpx
import numpy as np
import oracle
from service import NDJSON, Output, ndjson, spawn_server

from app import editfile
from app.items import Item, batch_of
from app.registry import Registry
from app.snapfile import SnapshotFiles
from app.stores import SQLiteStore
from spatial import scenes


def _kill(server) -> None:
    server.send_signal(signal.SIGKILL)
    server.communicate(timeout=10)


def _integrity(data_dir) -> str:
    db = sqlite3.connect(data_dir / "vantage.sqlite3")
    try:
        return db.execute("PRAGMA integrity_check").fetchone()[0]
    finally:
        db.close()


def _wait_for_a_staged_row(data_dir) -> None:
    """Until a row of a new base is in the store, beside the base's own (a second rowset)."""
    db = sqlite3.connect(data_dir / "vantage.sqlite3")
    try:
        deadline = time.monotonic() + 60
        while db.execute("SELECT count(DISTINCT rowset) FROM bases").fetchone()[0] < 2:
            assert time.monotonic() < deadline, "no row of the import was staged"
            time.sleep(0.01)
    finally:
        db.close()


def _shown(url: str, doc: str, rect) -> dict[str, tuple]:
    params = {**dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)), "limit": 100_000}
    items = httpx.get(f"{url}/documents/{doc}/viewport", params=params, timeout=30).json()["items"]
    return {item["id"]: (item["x0"], item["y0"], item["x1"], item["y1"]) for item in items}


def test_a_kill_mid_import_leaves_the_last_committed_version(tmp_path):
    first, _ = scenes.long_document(pages=4, seed=1)
    second = scenes.long_document(pages=600, seed=2)[0] + 5.0  # overlaps the first's ids, moved
    server, url = spawn_server(tmp_path, "--log-level", "info")
    output = Output(server)
    try:
        doc = httpx.post(f"{url}/documents", json={"name": "report"}).json()["id"]
        assert (
            httpx.post(f"{url}/documents/{doc}/items", content=ndjson(first), headers=NDJSON).json()[
                "version"
            ]
            == 1
        )
        body = ndjson(second)

        def big_import() -> None:
            with contextlib.suppress(httpx.TransportError):  # the server dies under it, as intended
                httpx.post(f"{url}/documents/{doc}/items", content=body, timeout=60, headers=NDJSON)

        importer = threading.Thread(target=big_import)
        importer.start()
        output.wait_for(f"import into {doc}: storing")  # merged: building, its rows staged
        _wait_for_a_staged_row(tmp_path)
        server.send_signal(signal.SIGKILL)
        importer.join()
    finally:
        output.stop()  # reaps it, and reads what it printed before it died
    assert "committed version 2" not in str(output)  # the kill landed mid-import
    server, url = spawn_server(tmp_path)
    try:
        described = httpx.get(f"{url}/documents/{doc}").json()
        assert described["version"] == 1 and described["items"] == len(first)
        for rect in ((0.0, 0.0, 700.0, 900.0), (0.0, 1500.0, 700.0, 3000.0)):
            truth = {f"i{i}": tuple(first[i]) for i in np.flatnonzero(oracle.hits(first, rect))}
            assert _shown(url, doc, rect) == truth
    finally:
        _kill(server)
    assert _integrity(tmp_path) == "ok"
    store = SQLiteStore(tmp_path)  # the rows the killed import staged are no base's: swept
    try:
        assert store.sweep_rows(grace=0) >= 1
        assert store._rows("SELECT count(DISTINCT rowset) FROM bases")[0][0] == 1
        assert len(store.read_base(doc)) == len(first)
    finally:
        store.close()


def test_a_kill_mid_edits_keeps_every_acknowledged_edit(tmp_path):
    server, url = spawn_server(tmp_path)
    acked: dict[str, tuple] = {}
    try:
        doc = httpx.post(f"{url}/documents", json={"name": "board"}).json()["id"]
        base = np.array([[0.0, 0.0, 10.0, 10.0]])
        assert (
            httpx.post(f"{url}/documents/{doc}/items", content=ndjson(base), headers=NDJSON).json()["version"]
            == 1
        )
        stop = threading.Event()

        def edit() -> None:
            with httpx.Client(base_url=url) as c:
                for k in range(100_000):
                    box = (float(k), 0.0, float(k) + 1, 1.0)
                    try:
                        answer = c.put(
                            f"/documents/{doc}/items/e{k % 50}",
                            json=dict(zip(("x0", "y0", "x1", "y1"), box, strict=True)),
                        )
                    except httpx.TransportError:
                        return
                    assert answer.status_code in (200, 201)
                    acked[f"e{k % 50}"] = (box, answer.json()["version"])
                    if stop.is_set():
                        return

        editor = threading.Thread(target=edit)
        editor.start()
        time.sleep(0.8)
        _kill(server)
        stop.set()
        editor.join()
        assert len(acked) == 50  # the burst got well going
        server, url = spawn_server(tmp_path)
        described = httpx.get(f"{url}/documents/{doc}").json()
        last_acked = max(version for _, version in acked.values())
        assert described["version"] in (last_acked, last_acked + 1)  # + the one unanswered, if it committed
        for item_id, (box, _version) in acked.items():
            stored = httpx.get(f"{url}/documents/{doc}/items/{item_id}").json()
            got = (stored["x0"], stored["y0"], stored["x1"], stored["y1"])
            # the acknowledged box, or (only for the in-flight edit) the one after it
            assert got == box or (described["version"] == last_acked + 1 and got[0] == box[0] + 50), item_id
        assert described["items"] == 51
    finally:
        _kill(server)
    assert _integrity(tmp_path) == "ok"


def test_edits_are_saved_soon_after_they_are_made_so_a_kill_leaves_none_to_replay(tmp_path):
    """A few edits, far fewer than a save's count, then nothing: they are saved beside the base
    ``VANTAGE_SAVE_EDITS_SECONDS`` after the first, with no edit after them to prompt it. A
    kill then leaves the next open none to replay from the store."""
    server, url = spawn_server(tmp_path, env={"VANTAGE_SAVE_EDITS_SECONDS": "0.5"})
    try:
        doc = httpx.post(f"{url}/documents", json={"name": "board"}).json()["id"]
        boxes = np.array([[k, 0.0, k + 1.0, 1.0] for k in range(300)])
        httpx.post(f"{url}/documents/{doc}/items", content=ndjson(boxes), headers=NDJSON).raise_for_status()
        for k in range(3):
            answer = httpx.put(
                f"{url}/documents/{doc}/items/i{k}", json={"x0": k, "y0": 5, "x1": k + 1, "y1": 6}
            )
            answer.raise_for_status()
        version = answer.json()["version"]
        deadline = time.monotonic() + 30
        while not any(
            editfile.saved_version(p) == version for p in (tmp_path / "snapshots").glob("*.vedits")
        ):
            assert time.monotonic() < deadline, "the edits were not saved beside the base"
            time.sleep(0.05)
    finally:
        _kill(server)
    store = SQLiteStore(tmp_path)
    try:
        reopened = Registry(store, SnapshotFiles(tmp_path / "snapshots"), 1 << 30)[doc]
        assert reopened.edits_saved[1] == 3 and reopened.snapshot.version == version  # none replayed
        assert reopened.snapshot.tree.get(reopened.snapshot.position("i2")) == (2.0, 5.0, 3.0, 6.0)
    finally:
        store.close()


def _backup(database, into) -> None:
    """A copy of the SQLite database ``database`` as its backup makes it (the WAL's commits in it)."""
    source, target = sqlite3.connect(database), sqlite3.connect(into)
    try:
        source.backup(target)
    finally:
        source.close()
        target.close()


def _restore(backup, data_dir) -> None:
    """The store put back as the backup holds it, as an operator restores one (server stopped)."""
    _backup(backup, data_dir / "vantage.sqlite3")


def _moves(url: str, doc: str, x0: float, count: int) -> int:
    """``count`` items moved to ``x0`` over HTTP, each acknowledged; the last version."""
    with httpx.Client(base_url=url) as c:
        for k in range(count):
            answer = c.put(
                f"/documents/{doc}/items/i{k}", json={"x0": x0, "y0": k, "x1": x0 + 1, "y1": k + 1}
            )
            assert answer.status_code == 200, answer.text
    return answer.json()["version"]


def test_a_store_restored_from_a_backup_never_shows_the_edits_saved_after_it(tmp_path):
    """The edits saved beside the base after a backup (x0=20) are passed over once the store is
    restored from it, and removed: the 10 edits acknowledged since (x0=30), which bring the
    document back to the same version, are what a restart after a kill shows."""
    boxes = np.array([[k, 0.0, k + 1.0, 1.0] for k in range(300)])
    server, url = spawn_server(tmp_path)
    try:
        doc = httpx.post(f"{url}/documents", json={"name": "board"}).json()["id"]
        httpx.post(f"{url}/documents/{doc}/items", content=ndjson(boxes), headers=NDJSON).raise_for_status()
    finally:
        server.terminate()
        server.communicate(timeout=10)
    _backup(tmp_path / "vantage.sqlite3", tmp_path / "backup.sqlite3")
    server, url = spawn_server(tmp_path)
    try:
        discarded = _moves(url, doc, 20.0, 10)
    finally:
        server.terminate()  # a clean stop saves the edits beside the base
        server.communicate(timeout=10)
    assert [editfile.saved_version(p) for p in (tmp_path / "snapshots").glob("*.vedits")] == [discarded]
    _restore(tmp_path / "backup.sqlite3", tmp_path)
    server, url = spawn_server(tmp_path)
    try:
        assert _moves(url, doc, 30.0, 10) == discarded  # acknowledged, at the versions of the discarded
    finally:
        _kill(server)  # before any save of them
    server, url = spawn_server(tmp_path)
    try:
        shown = [httpx.get(f"{url}/documents/{doc}/items/i{k}").json()["x0"] for k in range(10)]
        assert shown == [30.0] * 10
    finally:
        _kill(server)


def _batch(items: list[tuple[str, tuple]]):
    return batch_of([Item(item_id, *box, kind="note") for item_id, box in items], 4096)


def _imported(registry: Registry, n: int = 300):
    doc = registry.create("board")
    doc.import_items([_batch([(f"i{k}", (k, 0.0, k + 1.0, 1.0)) for k in range(n)])])
    return doc


def _move(doc, k: int, x0: float) -> int:
    return doc.put(_batch([(f"i{k}", (x0, k, x0 + 1.0, k + 1.0))]))[0]


def _saved(doc) -> None:
    """Wait for ``doc``'s edits being saved, if they are."""
    for thread in threading.enumerate():
        if thread.name == f"save edits of {doc.id}":
            thread.join()


def test_an_edit_file_newer_than_the_store_or_following_other_edits_is_removed(tmp_path, caplog):
    """A file of a version the store lost (restored from a backup) is passed over, removed and
    logged; and one put back after the store reached its version again with other edits is
    passed over too, as it records what it follows: the store's edits, not only a version."""
    store = SQLiteStore(tmp_path)
    files = SnapshotFiles(tmp_path / "snapshots")
    doc = _imported(Registry(store, files, 1 << 30))
    path = files.edits_path(doc.id, doc.snapshot.base_id)
    _backup(tmp_path / "vantage.sqlite3", tmp_path / "backup.sqlite3")
    for k in range(5):
        discarded = _move(doc, k, 20.0)
    doc.save_edits(every=1).join()
    assert editfile.saved_version(path) == discarded
    stale = path.read_bytes()
    store.close()
    _restore(tmp_path / "backup.sqlite3", tmp_path)
    store = SQLiteStore(tmp_path)
    try:
        with caplog.at_level(logging.WARNING, "vantage.snapshots"):
            doc = Registry(store, files, 1 << 30)[doc.id]
        assert not path.exists() and doc.edits_saved == (None, 0)
        assert f"of version {discarded}, newer than the store's 1" in caplog.text
        for k in range(5):
            assert _move(doc, k, 30.0) <= discarded
        path.write_bytes(stale)  # as a file the removal missed (another worker saved it meanwhile)
        caplog.clear()
        with caplog.at_level(logging.WARNING, "vantage.snapshots"):
            reopened = Registry(store, files, 1 << 30)[doc.id]
        assert not path.exists() and reopened.edits_saved == (None, 0)
        assert "it follows other edits" in caplog.text
        snap = reopened.snapshot
        assert [snap.tree.get(snap.position(f"i{k}"))[0] for k in range(6)] == [30.0] * 5 + [5.0]
        reopened.save_edits(every=1).join()  # saved again, and taken: they follow the store's
        assert Registry(store, files, 1 << 30)[doc.id].edits_saved == (snap.base_id, 5)
    finally:
        store.close()


def test_edits_a_full_disk_refuses_leave_no_file_and_are_saved_once_there_is_room(tmp_path, caplog):
    """A save of the edits that meets a full disk (ENOSPC, for real: its file's temporary name
    leads to /dev/full) leaves no part of a file, logs it, and the document edits on; the
    edits are saved again by their age, once there is room."""
    store = SQLiteStore(tmp_path)
    try:
        files = SnapshotFiles(tmp_path / "snapshots")
        doc = _imported(Registry(store, files, 1 << 30))
        path = files.edits_path(doc.id, doc.snapshot.base_id)
        version = _move(doc, 1, 20.0)
        full = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        full.symlink_to("/dev/full")
        with caplog.at_level(logging.WARNING, "vantage.snapshots"):
            doc.save_edits(every=1).join()
        assert "No space left on device" in caplog.text
        assert sorted(p.name for p in files.directory.iterdir()) == [f"{doc.id}.{doc.snapshot.base_id}.vsnap"]
        deadline = time.monotonic() + 30  # not taken for saved: tried again by age (20x the failed save)
        while (saving := doc.save_edits_older_than(0.0)) is None:
            assert time.monotonic() < deadline, "the edits a full disk refused were never tried again"
            time.sleep(0.01)
        saving.join()
        assert editfile.saved_version(path) == version
        assert _move(doc, 2, 20.0) == version + 1  # and it edits on
        assert Registry(store, files, 1 << 30)[doc.id].edits_saved == (doc.snapshot.base_id, 1)
    finally:
        store.close()


def test_edits_are_saved_beside_a_compactions_new_base_as_beside_the_old(tmp_path, monkeypatch):
    """The count of edits saved is of the base they were saved beside: a compaction's new base
    saves its own every ``SAVE_EDITS_EVERY``, not once they outnumber the old base's."""
    import app.documents

    monkeypatch.setattr(app.documents, "SAVE_EDITS_EVERY", 5)
    store = SQLiteStore(tmp_path)
    try:
        doc = _imported(Registry(store, SnapshotFiles(tmp_path / "snapshots"), 1 << 30))
        for k in range(7):
            _move(doc, k, 20.0)
            _saved(doc)
        assert doc.edits_saved[1] == 5
        doc.compact()
        for k in range(5):
            version = _move(doc, k, 30.0)
            _saved(doc)
        assert editfile.saved_version(doc.files.edits_path(doc.id, doc.snapshot.base_id)) == version
    finally:
        store.close()


def test_a_steady_stream_of_edits_is_saved_by_the_age_of_its_first_not_saved(tmp_path):
    """The clock of a save by age starts at the first edit not saved, not the last: edits that
    never stop coming are saved all the same."""
    store = SQLiteStore(tmp_path)
    try:
        doc = _imported(Registry(store, SnapshotFiles(tmp_path / "snapshots"), 1 << 30))
        path, saving = doc.files.edits_path(doc.id, doc.snapshot.base_id), None
        for k in range(40):  # one every 20 ms, for 0.8 s: saved by 0.3 s after the first
            _move(doc, k, 20.0)
            saving = saving or doc.save_edits_older_than(0.3)
            time.sleep(0.02)
        assert saving is not None, "edits coming every 20 ms were never saved by their age"
        saving.join()
        assert editfile.saved_version(path) is not None
    finally:
        store.close()


def test_a_document_closed_past_the_budget_saves_its_edits(tmp_path):
    """Closed to keep to the budget, a document saves its edits not saved yet: its next open
    replays none."""
    store = SQLiteStore(tmp_path)
    try:
        registry = Registry(store, SnapshotFiles(tmp_path / "snapshots"), budget=1)
        closed = _imported(registry)
        version = _move(closed, 3, 20.0)
        _imported(registry)  # used last: the first closes
        registry.evict()
        assert closed.id not in registry._open
        _saved(closed)
        assert editfile.saved_version(closed.files.edits_path(closed.id, closed.snapshot.base_id)) == version
    finally:
        store.close()


def test_a_save_never_overwrites_another_workers_newer_edit_file(tmp_path):
    """Two workers of one store: one behind the other saves its edits after the other saved
    newer ones; the newer file stays, and an open takes it."""
    store = SQLiteStore(tmp_path)
    try:
        files = SnapshotFiles(tmp_path / "snapshots")
        behind = _imported(Registry(store, files, 1 << 30))
        _move(behind, 1, 20.0)
        ahead = Registry(store, files, 1 << 30)[behind.id]
        _move(ahead, 2, 20.0)
        newest = _move(ahead, 3, 20.0)
        ahead.save_edits(every=1).join()
        behind.save_edits(every=1).join()  # not caught up: its snapshot is older
        path = files.edits_path(behind.id, behind.snapshot.base_id)
        assert editfile.saved_version(path) == newest
        assert Registry(store, files, 1 << 30)[behind.id].edits_saved[1] == 3
    finally:
        store.close()


def test_an_edit_after_an_open_took_edits_from_their_file_never_rebuilds_the_tree(tmp_path):
    """Edits past a tree's own rebuild threshold (256 + n/512), saved and taken at an open,
    leave the tree the room the document gives it until its compaction: the next edit does not
    rebuild it (at 1e8 items a minute and GBs)."""
    store = SQLiteStore(tmp_path)
    try:
        files = SnapshotFiles(tmp_path / "snapshots")
        doc = _imported(Registry(store, files, 1 << 30), n=2000)
        doc.edit([(f"i{k}", (k + 0.5, 2.0, k + 1.0, 3.0), b'{"id":"i%d"}' % k) for k in range(600)])
        doc.save_edits(every=1).join()
        reopened = Registry(store, files, 1 << 30)[doc.id]
        assert reopened.edits_saved == (doc.snapshot.base_id, 600) and not reopened.needs_compaction()
        taken = reopened.snapshot.tree._boxes
        _move(reopened, 700, 20.0)
        assert reopened.snapshot.tree._boxes is taken, "the edit after the open rebuilt the tree"
    finally:
        store.close()


def test_an_edit_file_with_any_byte_of_its_payload_flipped_is_passed_over(tmp_path, caplog):
    """An edit file's payload is checked against its sum before it is decoded: a flipped byte
    that still decompresses and decodes (zstd's frames here carry no checksum of their own) is
    passed over all the same, and the edits replayed from the store."""
    store = SQLiteStore(tmp_path)
    try:
        files = SnapshotFiles(tmp_path / "snapshots")
        doc = Registry(store, files, 1 << 30).create("d")
        boxes, _ = scenes.uniform(300, seed=4)
        doc.import_items([batch_of([Item(f"i{k}", *box) for k, box in enumerate(boxes.tolist())], 1 << 12)])
        for k in range(20):
            doc.put(batch_of([Item(f"i{k}", k, k, k + 1.5, k + 1)], 1 << 12))
        snap = doc.snapshot
        path = files.edits_path(doc.id, snap.base_id)
        assert editfile.save(path, snap, store, doc.id)
        data = path.read_bytes()
        header = len(data) - editfile._header(data)[1]
        expected = [snap.item_json(p) for p in snap.tree.query((0, 0, 2e6, 2e6)).tolist()]
        for place in range(header, len(data), max(1, (len(data) - header) // 150)):
            damaged = bytearray(data)
            damaged[place] ^= 0x01
            path.write_bytes(damaged)
            reopened = Registry(store, files, 1 << 30)[doc.id]
            assert reopened.edits_saved != (snap.base_id, snap.edits), f"byte {place} flipped, taken as it is"
            again = reopened.snapshot
            assert [again.item_json(p) for p in again.tree.query((0, 0, 2e6, 2e6)).tolist()] == expected
    finally:
        store.close()
