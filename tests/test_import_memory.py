"""An import's memory does not grow with its items' bytes: their bodies go to a spill file the
kernel pages, not to the process's heap. Measured as the benchmark measures it: the peak private
memory of a ``vantage import`` process, read from ``/proc`` while it runs."""

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

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
