"""The working set's rules, one at a time, on registries over a real store (two registries on
one store are two processes): the least recently used close past the budget, and a hit is a
use; a document in use or streamed never closes; another process's delete closes it here; a
document opened while another process commits is caught up at once; and every write first
catches its document up, so no process's write is lost."""

import asyncio
import gc

import pytest

import app.snapfile
from app.errors import Conflict, NotFound
from app.items import Item, batch_of
from app.registry import Registry
from app.snapfile import SnapshotFiles
from app.stores import SQLiteStore


def _registry(data_dir, budget: int = 1 << 30) -> Registry:
    return Registry(SQLiteStore(data_dir), SnapshotFiles(data_dir / "snapshots"), budget)


def _documents(registry: Registry, count: int) -> list[str]:
    """``count`` documents of the same 500 items: each holds the same bytes open."""
    items = [Item(f"i{k}", k, 0, k + 1, 1, "text", data={"text": f"w{k}"}) for k in range(500)]
    docs = []
    for k in range(count):
        doc = registry.create(f"d{k}")
        doc.import_items([batch_of(items, 4096)])
        docs.append(doc.id)
    return docs


@pytest.fixture
def three(tmp_path):
    """A registry holding three closed documents, and the bytes one holds open."""
    maker = _registry(tmp_path)
    docs = _documents(maker, 3)
    size = maker[docs[0]].nbytes
    registry = _registry(tmp_path, budget=0)  # another process's: none of them open yet
    assert registry.stats()["open"] == 0
    return registry, docs, size


def _open(registry: Registry) -> list[str]:
    return list(registry._open)


async def _follow(registry: Registry) -> None:
    """One look at the change log, and the catching up it starts: what the follower does
    every 50 ms, or when the store says something changed."""
    await registry.refresh()
    await registry.settle()


def test_past_the_budget_the_least_recently_used_close_and_a_hit_is_a_use(three):
    registry, (a, b, c), size = three
    registry.budget = 2 * size  # two fit
    registry[a], registry[b]
    registry[a]  # a hit: a is now the most recently used
    registry[c]
    registry.evict()
    assert _open(registry) == [a, c]  # b, used least recently, closed; not a, opened first


def _mapped(registry: Registry, doc_id: str) -> int:
    """How many of this process's mappings are of ``doc_id``'s snapshot files."""
    name = str(registry.files.directory / doc_id)
    with open("/proc/self/maps") as maps:
        return sum(1 for line in maps if name in line)


def test_a_closed_document_is_unmapped_at_once(three):
    """Not when the cyclic collector next runs (rarely, for long-lived objects): the working
    set's budget is kept in real memory."""
    registry, docs, _ = three
    gc.collect()
    gc.disable()
    try:
        for before, doc_id in zip([None, *docs], docs, strict=False):
            with registry.pinned(registry[doc_id]) as doc:
                assert doc.snapshot.tree.query((0, 0, 10, 1)).size
                assert _mapped(registry, doc_id) >= 1
            del doc
            assert _open(registry) == [doc_id]  # the most recently used stays, past the budget of 0
            if before is not None:  # closed as the next request ends, and unmapped then
                assert _mapped(registry, before) == 0, before
    finally:
        gc.enable()


def test_a_document_bigger_than_the_budget_stays_open_while_it_is_the_one_used(three):
    """Opened again for every request, it would replay its edits each time."""
    registry, (a, b, _), _ = three
    for _ in range(3):
        with registry.pinned(registry[a]) as doc:
            doc.put(batch_of([Item(f"e{doc.snapshot.version}", 0, 0, 1, 1)], 4096))
    assert _open(registry) == [a] and registry.stats()["opens"] == 1
    with registry.pinned(registry[b]):
        pass
    assert _open(registry) == [b]  # another used: the room is its


def test_a_document_in_use_or_streamed_never_closes(three):
    registry, (a, b, c), _ = three
    with registry.pinned(registry[a]):  # a request, or a stream, in flight
        registry[b]
        registry.evict()
        assert a in _open(registry)
    assert a not in _open(registry)  # closed as the request ends, past the budget
    unwatch = registry[b].watch(lambda: None)  # a stream's watcher
    registry[c]
    registry.evict()
    assert b in _open(registry)
    unwatch()
    registry.evict()
    assert b not in _open(registry)


def test_another_process_deleting_a_document_closes_it_here(tmp_path):
    here, there = _registry(tmp_path), _registry(tmp_path)
    (doc,) = _documents(here, 1)
    opened = there[doc]
    here.delete(doc)
    asyncio.run(_follow(there))
    assert opened.deleted  # its streams close with 4404
    with pytest.raises(NotFound):
        there[doc]


def test_a_document_opened_while_another_process_commits_is_caught_up_at_once(tmp_path, monkeypatch):
    here, there = _registry(tmp_path), _registry(tmp_path)
    (doc,) = _documents(here, 1)
    base = app.snapfile.SnapshotFiles.base

    def base_then_a_commit(files, store, meta, name=True, corrupt=None):
        snap = base(files, store, meta, name, corrupt)  # this process has read the document as it was...
        if files is there.files and not committed:
            committed.append(here[doc].put(batch_of([Item("late", 0, 0, 1, 1)], 4096))[0])
            asyncio.run(there.refresh())  # ...and its follower read the commit before the open ended
        return snap

    committed: list[int] = []
    monkeypatch.setattr(app.snapfile.SnapshotFiles, "base", base_then_a_commit)
    opened = there[doc]
    assert committed and opened.snapshot.version == committed[0]
    assert opened.snapshot.position("late") is not None


def test_every_write_first_catches_its_document_up(tmp_path):
    here, there = _registry(tmp_path), _registry(tmp_path)
    (doc,) = _documents(here, 1)
    behind = there[doc]  # open here and there
    version, _ = here[doc].put(batch_of([Item("from-here", 0, 0, 1, 1)], 4096))
    assert behind.snapshot.version < version  # there has not looked at the store since
    written, _ = behind.put(batch_of([Item("from-there", 2, 0, 3, 1)], 4096))
    assert written == version + 1
    snap = behind.snapshot
    assert snap.position("from-here") is not None and snap.position("from-there") is not None
    assert len(snap.tree) == 502


def test_a_version_never_written_is_a_conflict_at_once_not_after_the_patience(tmp_path):
    registry = _registry(tmp_path)
    (doc,) = _documents(registry, 1)
    document = registry[doc]

    async def ask() -> None:  # 60 s of patience for a store that is away; none for a version to come
        await asyncio.wait_for(registry.catch_up_to(document, document.snapshot.version + 5, 60.0), 10)

    with pytest.raises(Conflict, match="no such version has been written"):
        asyncio.run(ask())


def test_an_older_snapshot_is_never_shown_over_a_newer_one(tmp_path):
    """A catch-up that read the store before a write committed may finish after that write
    shows its own snapshot: what it brings is older, and is not shown."""
    registry = _registry(tmp_path)
    (doc,) = _documents(registry, 1)
    document = registry[doc]
    older = document.snapshot
    document.put(batch_of([Item("newer", 0, 0, 1, 1)], 4096))
    newer = document.snapshot
    document._publish(older)  # the late catch-up's
    assert document.snapshot is newer and newer.version == older.version + 1


def test_another_processs_compaction_has_its_followers_map_the_new_base(tmp_path):
    """A compaction changes no version (the items are the same), but its log row has each
    follower map the new base and let the old one go, which the compaction removed (a file
    still mapped takes its disk until then)."""
    maker = _registry(tmp_path)
    (doc_id,) = _documents(maker, 1)
    follower = _registry(tmp_path)
    here, there = follower[doc_id], maker[doc_id]
    for k in range(3):
        there.put(batch_of([Item(f"i{k}", k, 5, k + 1, 6, "text")], 4096))
    asyncio.run(_follow(follower))
    old = here.snapshot.base_id
    assert here.snapshot.version == there.snapshot.version and here.snapshot.edits == 3
    assert there.compact() == here.snapshot.version
    asyncio.run(_follow(follower))
    assert here.snapshot.base_id == there.snapshot.base_id != old
    assert here.snapshot.edits == 0 and here.snapshot.version == there.snapshot.version
    assert [here.snapshot.item_json(p) for p in range(500)] == [
        there.snapshot.item_json(p) for p in range(500)
    ]
