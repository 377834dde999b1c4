"""`vantage import` killed (SIGKILL) at each phase of its work: reading its file, writing the
new base's snapshot file, staging the store's rows, inside the commit, and just after it, on
each store. Killed before its commit, the document is the version before, whole; after, the
new one, whole. What the killed import left (staged rows, a half-written file) is swept, and
``vantage check`` finds every file whole.

Each kill is real: the import runs in a process of its own, the function it reaches in that
phase wrapped to send it SIGKILL on its Nth call."""

import signal
import subprocess
import sys
import textwrap

import orjson
import pytest

from app.cli import main
from app.config import get_settings
from app.registry import Registry
from app.snapfile import SnapshotFiles
from app.stores import open_store

# phase: (module, owner, function, the call it is killed at, committed by then)
KILLS = {
    "reading": ("app.table", "Spill", "write", 2, False),  # the decoded batches' JSON spilled
    "snapshot": ("app.snapfile", "Writer", "add", 3, False),  # its file half written
    "staging": ("", "", "_write_base_rows", 2, False),  # a row of it staged (``WRITING``: where)
    "commit": ("app.stores.base", "Writing", "import_base", 1, False),  # inside the transaction
    "committed": ("app.documents", "Document", "_show", 1, True),  # before it is shown
}

WRITING = {
    "sqlite": ("app.stores.sqlite", "_SQLiteWriting"),
    "postgres": ("app.stores.postgres", "_PostgresWriting"),
}

CHILD = textwrap.dedent(
    """
    import importlib, os, signal, sys
    import app.stores.base

    module, owner, name, at = sys.argv[1:5]
    app.stores.base.CHUNK = 1000  # rows of 1,000 items: a base of several rows
    target = getattr(importlib.import_module(module), owner)
    real, calls = getattr(target, name), [0]

    def killing(*args, **kwargs):
        calls[0] += 1
        if calls[0] == int(at):
            os.kill(os.getpid(), signal.SIGKILL)
        return real(*args, **kwargs)

    setattr(target, name, killing)
    from app.cli import main

    main(sys.argv[5:])
    """
)


def _items(data_dir, url) -> dict[str, list[float]]:
    """Each item's box, as a server opening the store would show it."""
    store = open_store(data_dir, url)
    try:
        registry = Registry(store, SnapshotFiles(data_dir / "snapshots"), 1 << 30)
        [meta] = store.documents()
        table = registry[meta["id"]].snapshot.table
        return dict(zip(map(table.item_id, range(len(table))), table.read_boxes().tolist(), strict=True))
    finally:
        store.close()


def _write(path, rows) -> None:
    path.write_bytes(b"".join(orjson.dumps(row) + b"\n" for row in rows))


def _rows(count: int, shift: float) -> list[dict]:
    return [
        {"id": f"i{n}", "x0": n + shift, "y0": -n, "x1": n + shift + 1.5, "y1": 2, "data": {"n": n}}
        for n in range(count)
    ]


@pytest.mark.parametrize("engine", ["sqlite", "postgres"])
@pytest.mark.parametrize("phase", list(KILLS))
def test_an_import_killed_at_each_phase_leaves_one_version_whole(
    tmp_path, phase, engine, request, monkeypatch
):
    url = request.getfixturevalue("database_url") if engine == "postgres" else ""
    monkeypatch.setenv("VANTAGE_DATABASE_URL", url)
    get_settings.cache_clear()
    data_dir = tmp_path / "data"
    first, second = tmp_path / "first.ndjson", tmp_path / "second.ndjson"
    _write(first, _rows(3000, 0.0))
    _write(second, _rows(8000, 0.25))  # the first's ids moved, and more
    main(["import", str(first), "--doc", "big", "--data-dir", str(data_dir)])
    before = _items(data_dir, url)
    module, owner, name, at, committed = KILLS[phase]
    if phase == "staging":  # each engine writes its rows its own way
        module, owner = WRITING[engine]
    command = ["import", str(second), "--doc", "big", "--data-dir", str(data_dir)]
    killed = subprocess.run(
        [sys.executable, "-c", CHILD, module, owner, name, str(at), *command],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert killed.returncode == -signal.SIGKILL, killed.stderr  # killed there, not done nor failed
    after = _items(data_dir, url)
    if committed:
        assert len(after) == 8000 and after["i5"] == [5.25, -5.0, 6.75, 2.0]
    else:
        assert after == before
    store = open_store(data_dir, url)
    try:
        store.sweep_rows(grace=0)
        SnapshotFiles(data_dir / "snapshots").sweep(store, grace=0)
        assert store._rows("SELECT count(DISTINCT rowset) FROM bases")[0][0] == 1
        [meta] = store.documents()
        assert meta["version"] == (2 if committed else 1)
    finally:
        store.close()
    left = sorted(p.name for p in (data_dir / "snapshots").iterdir())
    assert left == [f"{meta['id']}.{meta['base_id']}.vsnap"], left
    main(["check", "--data-dir", str(data_dir)])  # exits 1 if a file is corrupt
    assert _items(data_dir, url) == after  # and the sweep took nothing of it
