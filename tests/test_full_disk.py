"""A full disk anywhere in an import or a compaction (the body's spool, the items' spill, the
new base's snapshot file) is refused as the store's own full disk is: 507 saying what is full,
nothing left behind, the document as it was and still answering. An outside attack pass found
an import on a 20 MB tmpfs answering 500 with a traceback. The disk here is real: a small
tmpfs of the test's own, which the kernel fills."""

import contextlib
import os
import subprocess
from pathlib import Path

import orjson
import pytest
from service import NDJSON, client, ndjson

import app.routers.documents
import app.snapfile
from app.errors import StorageFull
from spatial import scenes

DISK_BYTES = 6 << 20
SCREEN = {"x0": -1e9, "y0": -1e9, "x1": 1e9, "y1": 1e9}


@pytest.fixture
def small_disk(tmp_path, monkeypatch):
    """The data directory on a tmpfs of ``DISK_BYTES``, mounted for the test."""
    if os.geteuid() != 0:
        pytest.skip("a full disk is a small tmpfs mounted for the test: mounting one needs root")
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={DISK_BYTES}", "tmpfs", str(disk)],
        capture_output=True,
        text=True,
    )
    if mounted.returncode:
        pytest.skip(f"a full disk is a small tmpfs mounted for the test, and mount failed: {mounted.stderr}")
    monkeypatch.setenv("VANTAGE_DATA_DIR", str(disk))
    yield disk
    subprocess.run(["umount", "--lazy", str(disk)], check=False)


def _body(items: int, data_bytes: int, at: float = 0.0) -> bytes:
    """NDJSON of ``items`` items, each with ``data_bytes`` of data (not compressible)."""
    lines = []
    for k in range(items):
        box = {"x0": at + k, "y0": at, "x1": at + k + 1, "y1": at + 1}
        lines.append(
            orjson.dumps({"id": f"big{k}", **box, "data": {"blob": os.urandom(data_bytes // 2).hex()}})
        )
    return b"\n".join(lines) + b"\n"


def _left(disk: Path) -> tuple[list[str], int]:
    """The names on the disk, and its bytes free (files with no name, still open, take room)."""
    stat = os.statvfs(disk)
    return sorted(str(p.relative_to(disk)) for p in disk.rglob("*")), stat.f_bavail * stat.f_frsize


def _unchanged(c, doc: str, disk: Path, before: tuple[list[str], int], items: int) -> None:
    """Nothing of the refused write is left on the disk, and the document answers as before."""
    names, free = _left(disk)
    assert names == before[0]  # no spill, spool or snapshot file, half or whole
    assert free >= before[1] - (256 << 10), (free, before[1])  # nor one with no name still open
    assert c.get(f"/documents/{doc}").json()["version"] == 1
    assert c.get(f"/documents/{doc}/viewport", params=SCREEN).json()["count"] == items
    assert c.get(f"/documents/{doc}/items/i0").status_code == 200


@contextlib.contextmanager
def _filled(disk: Path):
    """The disk filled to its last byte while the block runs, then freed."""
    filler = disk / "filler"
    try:
        with open(filler, "wb", buffering=0) as out, contextlib.suppress(OSError):
            while True:  # until the kernel says the disk is full
                out.write(bytes(64 << 10))
        assert _left(disk)[1] < 64 << 10
        yield
    finally:
        filler.unlink()


def _document(c) -> str:
    doc = c.post("/documents", json={"name": "d"}).json()["id"]
    answer = c.post(f"/documents/{doc}/items", content=ndjson(scenes.uniform(200, seed=1)[0]), headers=NDJSON)
    assert answer.status_code == 200, answer.text
    return doc


def test_a_full_disk_while_an_imports_items_are_spilled_is_a_507_that_leaves_nothing(small_disk):
    with client() as c:
        doc = _document(c)
        before = _left(small_disk)
        body = _body(2000, 3500)  # ~7 MB: held in memory as it arrives, then spilled to the disk
        answer = c.post(f"/documents/{doc}/items", content=body, headers=NDJSON)
        assert answer.status_code == 507, answer.text
        assert "data directory's disk is full" in answer.json()["detail"]
        assert "spilling the import's items" in answer.json()["detail"]
        _unchanged(c, doc, small_disk, before, 200)
        small = c.post(f"/documents/{doc}/items", content=_body(10, 100, at=1e6), headers=NDJSON)
        assert small.json() == {"imported": 10, "version": 2}  # the disk freed: imports go on


def test_an_imports_body_is_spooled_in_the_data_directory_and_a_full_disk_there_is_a_507(
    small_disk, monkeypatch
):
    """Spooled to the system's temp, the body would fill another disk, or be read whole
    there first; here the data directory's small disk is the one that fills."""
    monkeypatch.setattr(app.routers.documents, "SPOOL_IN_MEMORY", 64 << 10)
    with client() as c:
        doc = _document(c)
        before = _left(small_disk)
        answer = c.post(f"/documents/{doc}/items", content=_body(2000, 3500), headers=NDJSON)
        assert answer.status_code == 507, answer.text
        assert "data directory's disk is full" in answer.json()["detail"]
        assert "spooling the import's body" in answer.json()["detail"]
        _unchanged(c, doc, small_disk, before, 200)


def test_a_full_disk_while_a_new_base_is_built_refuses_the_import_and_the_compaction(small_disk, monkeypatch):
    """The disk fills as the import's snapshot file is built: refused (never built in memory
    instead: the store is on that disk too), its half file and staged rows gone. A compaction
    meeting it keeps its edits."""
    written = app.snapfile.write_base

    def on_a_full_disk(*args):
        with _filled(small_disk):
            return written(*args)

    with client() as c:
        doc = _document(c)
        store = c.app.state.registry.store
        before = _left(small_disk)
        monkeypatch.setattr(app.snapfile, "write_base", on_a_full_disk)
        answer = c.post(f"/documents/{doc}/items", content=_body(300, 100, at=1e6), headers=NDJSON)
        assert answer.status_code == 507, answer.text
        assert "data directory's disk is full" in answer.json()["detail"]
        assert "building the import's new base" in answer.json()["detail"]
        _unchanged(c, doc, small_disk, before, 200)
        assert store._rows("SELECT count(DISTINCT rowset) FROM bases WHERE doc_id = ?", doc)[0][0] == 1
        item = {"x0": 5, "y0": 5, "x1": 6, "y1": 6}
        assert c.put(f"/documents/{doc}/items/i0", json=item).status_code == 200
        document = c.app.state.registry[doc]
        with pytest.raises(StorageFull, match=r"disk is full.*building the compaction's new base"):
            document.compact()
        assert document.snapshot.edits == 1 and document.snapshot.version == 2
        assert store._rows("SELECT count(DISTINCT rowset) FROM bases WHERE doc_id = ?", doc)[0][0] == 1
        assert c.get(f"/documents/{doc}/items/i0").json()["x0"] == 5
        monkeypatch.setattr(app.snapfile, "write_base", written)
        assert document.compact() == 2 and document.snapshot.edits == 0  # room again: it folds


def test_an_upload_part_on_a_full_disk_is_a_507_that_keeps_the_upload(small_disk):
    with client() as c:
        doc = _document(c)
        upload = c.post(f"/documents/{doc}/uploads", json={}).json()["id"]
        before = _left(small_disk)
        part = c.put(f"/documents/{doc}/uploads/{upload}/parts/1", content=_body(2000, 3500))
        assert part.status_code == 507, part.text
        assert "data directory's disk is full" in part.json()["detail"]
        assert "keeping the upload's part" in part.json()["detail"]
        _unchanged(c, doc, small_disk, before, 200)  # no part, whole or half
        assert c.get(f"/documents/{doc}/uploads/{upload}").json()["parts"] == []
        small = _body(10, 100, at=1e6)
        assert c.put(f"/documents/{doc}/uploads/{upload}/parts/1", content=small).status_code == 200
        committed = c.post(f"/documents/{doc}/uploads/{upload}/commit", json={"parts": 1})
        assert committed.json() == {"imported": 10, "version": 2}
