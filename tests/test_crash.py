"""Crash safety: the real server killed with SIGKILL in the middle of an import and of a burst
of edits, then restarted: every committed version intact, nothing of the interrupted one."""

import contextlib
import signal
import sqlite3
import threading
import time

import httpx
import numpy as np
import oracle
from service import NDJSON, Output, ndjson, spawn_server

from app import editfile
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
