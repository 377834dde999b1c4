"""A document library on one host, on real server processes: start-up opens nothing, documents
open on demand and close past the memory budget with answers still exact, a damaged snapshot
file is rebuilt and never served, and with two workers every write is read by the next request
on either, every stream on either gets the push, and a worker killed mid-import loses nothing."""

import os
import signal
import threading
import time
from contextlib import ExitStack

import httpx
import numpy as np
import oracle
import orjson
import pytest
from service import NDJSON, Output, item_json, ndjson
from websockets.sync.client import connect

from app.launch import launch
from app.snapfile import read
from app.stores import SQLiteStore
from app.table import ItemTable
from spatial import scenes

SCREEN = (0.0, 0.0, 1500.0, 1500.0)


def _library(data_dir, docs: int, n: int) -> dict[str, np.ndarray]:
    """A store of ``docs`` uniform documents of ``n`` items, written straight to it: ``{id: boxes}``."""
    store = SQLiteStore(data_dir)
    library = {}
    for k in range(docs):
        boxes = scenes.uniform(n, seed=k)[0]
        doc = store.create_document(f"doc {k}")["id"]
        ids = [f"i{i}" for i in range(n)]
        bodies = [item_json(i, b) for i, b in zip(ids, boxes, strict=True)]
        store.write_items(doc, ItemTable.of(ids, boxes, bodies))
        library[doc] = boxes
    store.close()
    return library


def _serve(data_dir, *args: str, env: dict | None = None):
    server, url = launch(data_dir, *args, env=env)
    return server, url, Output(server)


def _stats(url: str) -> dict:
    with httpx.Client() as fresh:  # a new connection: any worker may answer it
        return fresh.get(f"{url}/stats").json()


def _check_viewport(url: str, doc: str, boxes: np.ndarray, rect=SCREEN) -> None:
    params = dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)) | {"limit": 100_000}
    with httpx.Client() as fresh:
        body = fresh.get(f"{url}/documents/{doc}/viewport", params=params).json()
    assert {e["id"] for e in body["items"]} == {f"i{i}" for i in np.flatnonzero(oracle.hits(boxes, rect))}


def test_start_up_opens_no_document_whatever_the_store_holds(data_dir):
    library = _library(data_dir, docs=40, n=3000)
    _, url, output = _serve(data_dir)
    try:
        stats = _stats(url)
        assert (stats["open"], stats["opens"], stats["held_bytes"]) == (0, 0, 0)
        listed = httpx.get(f"{url}/documents").json()  # listing reads the store's rows, opens nothing
        assert {d["id"]: d["items"] for d in listed} == {doc: 3000 for doc in library}
        assert _stats(url)["opens"] == 0
        doc, boxes = next(iter(library.items()))
        _check_viewport(url, doc, boxes)
        stats = _stats(url)
        assert (stats["open"], stats["opens"]) == (1, 1) and stats["held_bytes"] > 0
    finally:
        output.stop()


def test_a_small_budget_closes_the_least_recently_used_and_answers_stay_exact(data_dir):
    library = _library(data_dir, docs=8, n=20_000)
    _, url, output = _serve(data_dir, env={"VANTAGE_CACHE_MB": "8"})
    try:
        for _ in range(2):  # visit them in turn, twice: each open pushes out the oldest
            for doc, boxes in library.items():
                _check_viewport(url, doc, boxes)
        stats = _stats(url)
        assert stats["evictions"] >= 8 and stats["opens"] >= 9 and stats["held_bytes"] <= 8 << 20
        assert stats["open"] < len(library)
        with connect(f"{url.replace('http', 'ws')}/documents/{next(iter(library))}/stream") as ws:
            ws.send(orjson.dumps({"viewport": SCREEN}).decode())
            assert orjson.loads(ws.recv(timeout=10))["type"] == "view"
            for doc, boxes in library.items():  # a streamed document stays open through it all
                _check_viewport(url, doc, boxes)
            assert _stats(url)["open"] >= 1
    finally:
        output.stop()


def test_a_corrupt_or_stale_snapshot_file_is_rebuilt_never_served(data_dir):
    boxes = scenes.uniform(5000, seed=3)[0]
    _, url, output = _serve(data_dir)
    try:
        doc = httpx.post(f"{url}/documents", json={"name": "d"}).json()["id"]
        httpx.post(f"{url}/documents/{doc}/items", content=ndjson(boxes), headers=NDJSON).raise_for_status()
        (first,) = (data_dir / "snapshots").glob(f"{doc}.*.vsnap")
        older = first.read_bytes()  # the file of a base about to be replaced
        moved = boxes + 10_000.0
        httpx.post(f"{url}/documents/{doc}/items", content=ndjson(moved), headers=NDJSON).raise_for_status()
    finally:
        output.stop()
    (current,) = (data_dir / "snapshots").glob(f"{doc}.*.vsnap")
    assert current != first and not first.exists()  # the replaced base's file is gone
    _, _, _, blocks = read(current)
    root = blocks.start + next(lo for lo, _, name in blocks.names if name == "tree.nodes")
    for damage in ("stale", "corrupt"):
        data = bytearray(older) if damage == "stale" else bytearray(current.read_bytes())
        if damage == "corrupt":  # the root's record: the first request reads it
            data[root] ^= 0x5A
        current.write_bytes(data)
        _, url, output = _serve(data_dir)
        try:
            _check_viewport(url, doc, moved, (10_000.0, 10_000.0, 11_500.0, 11_500.0))
            _check_viewport(url, doc, moved, SCREEN)  # nothing of the old base is shown
            assert _stats(url)["rebuilt"] == 1
        finally:
            output.stop()
        assert "rebuilt from the store" in str(output)
    assert "tree.nodes" in str(output) and "is corrupt" in str(output)  # the log names the bad block's array


@pytest.fixture
def two_workers(data_dir):
    """`vantage serve --workers 2` with a 2,000-item document: ``(url, doc, boxes, output)``."""
    boxes = scenes.uniform(2000, seed=9)[0]
    _, url, output = _serve(data_dir, "--workers", "2", "--log-level", "info")
    try:
        doc = httpx.post(f"{url}/documents", json={"name": "shared"}).json()["id"]
        httpx.post(f"{url}/documents/{doc}/items", content=ndjson(boxes), headers=NDJSON).raise_for_status()
        yield url, doc, boxes, output
    finally:
        output.stop()


def test_a_write_on_one_worker_is_read_by_the_next_request_on_either(two_workers):
    url, doc, _, _ = two_workers
    workers = set()
    for k in range(300):  # every request on a new connection: the workers take them as they come
        if k >= 40 and len(workers) == 2:
            break
        box = {"x0": 5.0 * k, "y0": 5.0, "x1": 5.0 * k + 3, "y1": 8.0}
        with httpx.Client() as fresh:
            version = fresh.put(f"{url}/documents/{doc}/items/new{k}", json=box).json()["version"]
        with httpx.Client() as fresh:
            item = fresh.get(f"{url}/documents/{doc}/items/new{k}")
        assert item.status_code == 200 and {key: item.json()[key] for key in box} == box
        with httpx.Client() as fresh:
            assert fresh.get(f"{url}/documents/{doc}").json()["version"] >= version
        workers.add(_stats(url)["worker"])
    assert len(workers) == 2


def test_an_edit_reaches_the_streams_on_every_worker(two_workers):
    url, doc, _, _ = two_workers
    streams, workers = [], set()
    with ExitStack() as stack:
        for seq in range(200):  # until both workers hold some: the kernel picks the acceptor
            ws = stack.enter_context(connect(f"{url.replace('http', 'ws')}/documents/{doc}/stream"))
            streams.append(ws)
            workers.add(ws.response.headers["x-vantage-worker"])
            ws.send(orjson.dumps({"seq": seq, "viewport": SCREEN}).decode())
            assert orjson.loads(ws.recv(timeout=10))["type"] == "view"
            if len(workers) == 2 and len(streams) >= 8:
                break
        assert len(workers) == 2
        box = {"x0": 10.0, "y0": 10.0, "x1": 20.0, "y1": 20.0}
        version = httpx.put(f"{url}/documents/{doc}/items/pushed", json=box).json()["version"]
        for ws in streams:
            pushed = orjson.loads(ws.recv(timeout=10))
            assert (pushed["type"], pushed["version"]) == ("edit", version)
            assert [e["id"] for e in pushed["enter"]] == ["pushed"]


def test_a_worker_killed_mid_import_loses_nothing_committed(two_workers):
    url, doc, boxes, output = two_workers
    big = ndjson(scenes.uniform(600_000, seed=10)[0] + 1e6)
    started = time.monotonic()

    storing = f"import into {doc}: storing 600000 items"  # this import's (its ids i0... replace the first)

    def kill_the_importer() -> None:
        output.wait_for(storing, timeout=120)  # inside the store's transaction now
        line = next(line for line in output.lines if storing in line)
        os.kill(int(line.rsplit("worker ", 1)[1].rstrip(")\n")), signal.SIGKILL)

    killer = threading.Thread(target=kill_the_importer)
    killer.start()
    with pytest.raises(httpx.TransportError):  # the worker died under it
        httpx.post(f"{url}/documents/{doc}/items", content=big, headers=NDJSON, timeout=120)
    killer.join()
    assert time.monotonic() - started < 120
    for _ in range(6):  # the other worker (and the one started in its place) answer as before
        with httpx.Client() as fresh:
            described = fresh.get(f"{url}/documents/{doc}").json()
        assert described["version"] == 1 and described["items"] == len(boxes)
        _check_viewport(url, doc, boxes)
        _check_viewport(url, doc, boxes, (1e6, 1e6, 2e6, 2e6))  # none of the killed import


def test_a_base_written_without_a_server_is_built_once_into_one_file(data_dir):
    library = _library(data_dir, docs=2, n=3000)
    _, url, output = _serve(data_dir)
    try:
        for doc, boxes in library.items():
            _check_viewport(url, doc, boxes)
    finally:
        output.stop()
    files = sorted(p.name.split(".")[0] for p in (data_dir / "snapshots").glob("*.vsnap"))
    assert files == sorted(library)  # one file a document, none orphaned
    store = SQLiteStore(data_dir)
    named = {doc: store.document(doc)["base_id"] for doc in library}
    store.close()
    assert all((data_dir / "snapshots" / f"{doc}.{base}.vsnap").exists() for doc, base in named.items())
