"""An import's memory does not grow with its items' bytes: their bodies go to a spill file the
kernel pages, not to the process's heap. Measured as the benchmark measures it: the peak private
memory of a ``vantage import`` process, read from ``/proc`` while it runs."""

import json
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest
from service import in_fresh_interpreter

from app.registry import Registry
from app.snapfile import SnapshotFiles
from app.stores import SQLiteStore
from benchmarks.scale import private_bytes

ITEMS = 30_000
PAYLOAD = 4_000  # bytes of data an item: 120 MB for ITEMS


def _write(path: Path, items: int) -> Path:
    with open(path, "w") as out:
        for i in range(items):
            item = {"id": f"i{i}", "x0": i % 300 * 10, "y0": i // 300 * 10, "x1": i % 300 * 10 + 8}
            item |= {"y1": i // 300 * 10 + 8, "kind": "note", "data": {"blob": "x" * PAYLOAD}}
            out.write(json.dumps(item) + "\n")
    return path


def _peak_import(path: Path, data_dir: Path) -> int:
    """Peak private bytes of ``vantage import path --doc d --data-dir data_dir``."""
    command = [
        sys.executable,
        "-m",
        "app.cli",
        "import",
        str(path),
        "--doc",
        "d",
        "--data-dir",
        str(data_dir),
    ]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    peak = [0]

    def sample() -> None:
        while process.poll() is None:
            peak[0] = max(peak[0], private_bytes(process.pid))
            time.sleep(0.005)

    sampler = threading.Thread(target=sample)
    sampler.start()
    _, err = process.communicate()
    sampler.join()
    assert process.returncode == 0, err.decode()
    return peak[0]


@pytest.mark.slow(seconds=30)
@pytest.mark.timeout(600)  # eight imports, each a process: ~50 s alone, minutes beside other work
def test_an_imports_memory_does_not_grow_with_its_items_bytes(tmp_path):
    """Twice the items cost twice the ids, boxes and index (~12 MB more here), not their bytes
    (120 MB more): what a step of the import holds at once (a block read, a row written) is
    the same for both."""
    one, two = _write(tmp_path / "one.ndjson", ITEMS), _write(tmp_path / "two.ndjson", 2 * ITEMS)
    extra = two.stat().st_size - one.stat().st_size
    for _ in range(2):  # any kernel not compiled yet, a new import's or an upsert's, is compiled now
        _peak_import(one, tmp_path / "warm")
    # Sampling can only miss a peak, and a short import's most: each base is the higher of two.
    # An upsert of every id (merged with what is stored) is measured against an upsert (the
    # same file imported again into each store): it holds both versions' ids and boxes, and
    # one more pass's step of mapped pages.
    base = max(_peak_import(one, tmp_path / "one"), _peak_import(one, tmp_path / "one again"))
    base_upsert = max(_peak_import(one, tmp_path / "one"), _peak_import(one, tmp_path / "one again"))
    first = _peak_import(two, tmp_path / "two")
    again = _peak_import(two, tmp_path / "two")
    # Held in memory, the bodies would cost their bytes at least once more (they cost 2-3x).
    assert first - base < extra / 3, (base, first, extra)
    assert again - base_upsert < extra / 3, (base_upsert, again, extra)
    store = SQLiteStore(tmp_path / "two")
    try:
        registry = Registry(store, SnapshotFiles(tmp_path / "two" / "snapshots"), 1 << 30, 10)
        (meta,) = store.documents()
        snap = registry[meta["id"]].snapshot
        assert len(snap.tree) == 2 * ITEMS and snap.version == 2
        for pos in (0, ITEMS, 2 * ITEMS - 1):
            item = json.loads(bytes(snap.item_json(pos)))
            assert item["id"] == snap.item_id(pos) and item["data"]["blob"] == "x" * PAYLOAD
    finally:
        store.close()
    assert not list((tmp_path / "two" / "snapshots").glob(".*"))  # no spill file is left behind


HEAP_AT_MERGE = textwrap.dedent(
    """
    import io, json, os, sys, tempfile
    from pathlib import Path
    import app.main; app.main.start_up()  # the server's start-up: large blocks mapped on their own
    from app.documents import pack
    from app.heap import return_freed_memory
    from app.items import decode_ndjson
    from app.table import ItemTable
    from benchmarks.scale import private_bytes

    body = b"".join(
        b'{"id":"i%d","x0":%d,"y0":0,"x1":%d,"y1":1,"data":{"t":"%s"}}\\n' % (k, k, k + 1, b"w" * (k % 2000))
        for k in range(int(sys.argv[1]))
    )
    merge, held = ItemTable.merge, []

    def merging(tables, *args, **kwargs):
        held.append(private_bytes(os.getpid()) - before)
        return merge(tables, *args, **kwargs)

    ItemTable.merge = staticmethod(merging)
    return_freed_memory()  # the body's making
    before = private_bytes(os.getpid())
    with tempfile.TemporaryDirectory() as spill:
        pack(decode_ndjson(io.BytesIO(body), 1 << 16, 4096), Path(spill))
    print(json.dumps({"held": held[0], "body": len(body)}))
    """
)


def test_an_import_hands_its_decoded_batches_heap_back_before_the_merge():
    """The decoded batches (Python strings and items, ~2x a batch's bytes) are freed once
    spilled, but glibc keeps their heap: handed back before the merge, or the merge and the
    build that follow hold it at their peak (10 MB here, a batch of 16k items of ~1 kB). Read
    once, as the merge begins, in a fresh process: no sampling, nothing timed."""
    measured = in_fresh_interpreter(HEAP_AT_MERGE, "20000", timeout=120)
    assert isinstance(measured, dict)
    assert measured["held"] < measured["body"] / 5, measured  # ~1 MB handed back, ~10 MB kept
