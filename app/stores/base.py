"""The one interface every store implements, and what the engines share.

A document is a base, its items as a few column blobs written by the last import, plus the
single-item edits since (the last of each item). Every write is one transaction on one
document, begun by ``writing(doc_id)``, which locks the document against every other writer
(another worker, another replica) until it commits or rolls back: a failed import rolls back
whole, so nothing half-written survives it, and a document's versions are gap-free.

A base's rows are a rowset, which the document's row names. A compaction writes its new
base's rows under a new rowset, in short transactions of their own while edits go on, then
points the document at them in one short write, and deletes the old rowset after.

Every committed write also appends a row to the change log, in the same transaction: which
document reached which version, and how (an import, an edit, a deletion). The log's ``seq``
orders rows as their transactions committed, so a process that follows the log from the last
``seq`` it saw (``log_after``) misses nothing, whenever it looks and however long it was away.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import secrets
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractAsyncContextManager, AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zstandard

from spatial.paging import in_steps

from ..errors import ServiceError
from ..items import boxes_of
from ..table import Edit, ItemTable, Packed, release

__all__ = [
    "CHUNK",
    "CHUNK_BYTES",
    "Change",
    "Edit",
    "Staged",
    "Store",
    "StoreError",
    "StoreUnavailable",
    "Writing",
]

# A base row holds at most this many items, and bodies of at most this many bytes: blobs stay
# far below either engine's limit on one value (1 GB), and a write holds a few rows' bytes at once
CHUNK, CHUNK_BYTES = 1 << 18, 1 << 24
# A base row's codec: its blobs as they are (before format 5); zstd frames; zstd frames without
# the boxes, each read back from its item's JSON (one copy of each box in the store, not two)
RAW, ZSTD, LEAN = 0, 1, 2
ZSTD_LEVEL = 1  # a 1M board's JSON: 41 B an item at 0.3 us (level 3: 47 B at 0.7 us)
ROWS_GRACE_SECONDS = 3600.0  # rows of no base begun more recently may be a compaction's under way
META = ("id", "name", "created", "version", "base_id", "base_version", "items", "bounds")
META_QUERY = f"SELECT {', '.join(META)} FROM documents"
STAGED = "FROM bases WHERE doc_id = ? AND rowset = ?"  # a rowset's rows
DROP_ROW = f"""
DELETE {STAGED} AND rowset != (SELECT rowset FROM documents WHERE id = ?)
    AND chunk = (SELECT min(chunk) {STAGED})
"""
EDIT = """
INSERT INTO edits VALUES (?, ?, ?, ?, ?, ?, ?, ?)
ON CONFLICT (doc_id, item_id) DO UPDATE SET version = excluded.version,
    x0 = excluded.x0, y0 = excluded.y0, x1 = excluded.x1, y1 = excluded.y1, body = excluded.body
"""


class StoreError(RuntimeError):
    """The store cannot be used as it is; the message says what to do."""


class StoreUnavailable(ServiceError):
    """The store cannot be reached now (its server is down or restarting); nothing was written.
    Documents already open keep answering reads from what they hold."""

    status = 503
    retry_after = 2


@dataclass(frozen=True)
class Change:
    """One row of the change log: ``doc_id`` reached ``version`` by an import, an edit or a
    deletion; ``seq`` orders rows as they committed."""

    seq: int
    doc_id: str
    version: int
    kind: str  # "import", "edit", "delete" or "compact" (a new base, the same items)


class Writing(ABC):
    """One write transaction on one document, its row locked: ``meta`` is the row as it
    stands. The ``write_*`` methods are the transaction's; it commits when the ``with``
    block ends and rolls back if it raises. The SQL is the engines' common dialect, written
    with ``?`` placeholders (``PARAM``: the engine driver's style); an engine supplies how
    many rows go in at a time (``executemany``, or ``COPY``), and may add to how the change
    log is appended to."""

    PARAM = "?"

    def __init__(self, db: Any, meta: dict[str, Any]) -> None:
        self._db, self.meta, self._id = db, meta, meta["id"]

    def bump(self) -> int:
        """The document's next version, which this transaction writes."""
        row = self._sql("UPDATE documents SET version = version + 1 WHERE id = ? RETURNING version", self._id)
        self.meta["version"] = version = int(row.fetchone()[0])
        return version

    def write_base(
        self, table: ItemTable, version: int, base_id: str | None, bounds: Iterable[float] | None
    ) -> None:
        """Make ``table`` the document's whole content at ``version``, its base named ``base_id``.
        Every other row of the document goes, a compaction's staged ones too (which then finds
        its base replaced)."""
        self._sql(
            "UPDATE documents SET items = ?, bounds = ? WHERE id = ?",
            len(table),
            bounds_json(bounds),
            self._id,
        )
        self._sql("DELETE FROM bases WHERE doc_id = ?", self._id)
        rowset = new_rowset()
        pack = packer()
        self._write_base_rows((self._id, rowset, *encoded(row, pack)) for row in chunks(table))
        self._point(rowset, version, base_id)
        self._log(version, "import")

    def import_base(
        self, staged: Staged, version: int, base_id: str, items: int, bounds: Iterable[float] | None
    ) -> int:
        """Make the rows ``staged`` (``Store.stage_base``) the document's whole content at
        ``version``, its base named ``base_id``, of ``items`` items within ``bounds``: an import
        built outside the write. The rowset it replaces, for ``Store.drop_rows`` once this
        commits.

        :raises StoreError: as ``compact_base``
        """
        self._sql(
            "UPDATE documents SET items = ?, bounds = ? WHERE id = ?", items, bounds_json(bounds), self._id
        )
        old = self._swap(staged, version, base_id)
        self._log(version, "import")
        return old

    def compact_base(self, staged: Staged, version: int, base_id: str) -> int:
        """Make the rows ``staged`` (``Store.stage_base``) the document's base as of ``version``
        (its items, some edited since maybe, as their last edit left them), named ``base_id``:
        the edits since ``version`` stay, and the document's version, items and bounds do not
        change. The rowset it replaces, for ``Store.drop_rows`` once this commits.

        :raises StoreError: if some of the staged rows are gone (swept as left by a killed
            compaction): nothing changes
        """
        old = self._swap(staged, version, base_id)
        self._log(self.meta["version"], "compact")
        return old

    def _swap(self, staged: Staged, version: int, base_id: str) -> int:
        """``_point`` at the rows ``staged``, if they are all there; the rowset replaced."""
        # Staged as chunks 0 to rows - 1, and dropped from the lowest up (``DROP_ROW``): those
        # left are one run, told by its ends, two lookups. A count compared every row's key,
        # and SQLite reads a row whose blobs overflow its page whole to compare it: the write
        # took 4.2 s at 1e8 items, every writer waiting (0.21 s at 1e7; 0.04 s by its ends).
        lo, hi = self._sql(
            f"SELECT (SELECT min(chunk) {STAGED}), (SELECT max(chunk) {STAGED})",
            *(self._id, staged.rowset) * 2,
        ).fetchone()
        held = 0 if lo is None else hi - lo + 1
        if held != staged.rows:
            raise StoreError(f"{staged.rows - held} of the {staged.rows} staged base rows are gone")
        old = self._sql("SELECT rowset FROM documents WHERE id = ?", self._id).fetchone()[0]
        self._point(staged.rowset, version, base_id)
        return int(old)

    def _point(self, rowset: int, version: int, base_id: str | None) -> None:
        """The rows of ``rowset`` as the base at ``version``, without the edits up to it."""
        self._sql(
            "UPDATE documents SET base_id = ?, base_version = ?, rowset = ? WHERE id = ?",
            base_id,
            version,
            rowset,
            self._id,
        )
        self._sql("DELETE FROM edits WHERE doc_id = ? AND version <= ?", self._id, version)
        # The log reaches back to the base, as far as an edit's diff can
        self._sql("DELETE FROM changes WHERE doc_id = ? AND version < ?", self._id, version)

    def write_edits(
        self,
        version: int,
        edits: list[tuple[str, tuple | None, bytes | None]],
        items: int,
        bounds: Iterable[float] | None,
    ) -> None:
        """Store ``edits``, ``(item id, box, body)`` each at ``version`` (box and body None:
        deleted), and the document's item count and bounds after them."""
        rows = [(self._id, item_id, version, *(box or (None,) * 4), body) for item_id, box, body in edits]
        self._executemany(EDIT.replace("?", self.PARAM), rows)
        self._sql(
            "UPDATE documents SET items = ?, bounds = ? WHERE id = ?", items, bounds_json(bounds), self._id
        )
        self._log(version, "edit")

    def set_base_id(self, base_id: str) -> None:
        """Name the document's base, which had no name (one written by ``write_items``)."""
        self._sql("UPDATE documents SET base_id = ? WHERE id = ? AND base_id IS NULL", base_id, self._id)

    def delete(self) -> None:
        """Delete the document, its base and its edits (its log rows but the deletion's)."""
        self._sql("DELETE FROM documents WHERE id = ?", self._id)
        self._sql("DELETE FROM changes WHERE doc_id = ?", self._id)
        self._log(self.meta["version"], "delete")

    def _log(self, version: int, kind: str) -> None:
        """Append to the change log: the last statement of every write."""
        self._sql("INSERT INTO changes (doc_id, version, kind) VALUES (?, ?, ?)", self._id, version, kind)

    def _sql(self, text: str, *args: object) -> Any:
        return self._db.execute(text.replace("?", self.PARAM), args)

    @abstractmethod
    def _executemany(self, text: str, rows: list[tuple]) -> None: ...

    @abstractmethod
    def _write_base_rows(self, rows: Iterator[tuple]) -> None:
        """Insert ``rows`` into ``bases``: ``(doc_id, rowset, chunk, ids, id_offsets, bodies,
        body_offsets, boxes, codec)``."""


@dataclass
class Staged:
    """Base rows written by ``Store.stage_base``, which no read sees until ``import_base`` or
    ``compact_base`` points their document at them: their ``rowset``, and how many there are."""

    rowset: int
    rows: int = 0


def new_rowset() -> int:
    """A new rowset's number: the millisecond it was begun above 16 random bits, so the
    sweep can tell how old a rowset is, and two begun at once still differ."""
    return _first_rowset_at(time.time()) | secrets.randbits(16)


def _first_rowset_at(at: float) -> int:
    """The lowest number of a rowset begun at ``at`` (seconds) or later."""
    return int(at * 1000) << 16


class Store(ABC):
    """Documents and their items. Methods raise NotFound for an unknown document and
    StoreUnavailable when the store cannot be reached."""

    engine: str  # "sqlite" or "postgresql"
    # Called (from any thread) when the engine hears of another process's commit, for a
    # follower to look at once instead of at its next poll; engines that cannot tell never call it.
    on_change: Callable[[], object] = staticmethod(lambda: None)

    def __init__(self) -> None:
        # The event loop's queue of writers: ``async with store.turn:`` before taking a thread,
        # so a long write (a large import) keeps the writers behind it out of the thread pool
        # that every reader needs (an engine whose writes lock less than the store says so).
        self.turn: AbstractAsyncContextManager[Any] = asyncio.Lock()

    @abstractmethod
    def close(self) -> None: ...

    # -- documents ---------------------------------------------------------------------------

    @abstractmethod
    def create_document(self, name: str, max_documents: int | None = None) -> dict[str, Any]:
        """A new, empty document.

        :raises Conflict: if the store holds ``max_documents`` already
        """

    def documents(self) -> list[dict[str, Any]]:
        """Every document's row, oldest first."""
        return [meta_of(row) for row in self._rows(META_QUERY + " ORDER BY created")]

    @abstractmethod
    def document(self, doc_id: str) -> dict[str, Any]:
        """One document's row: id, name, created, version, base_id, base_version, items,
        bounds (a box containing every item, or None).

        :raises NotFound: if there is no such document
        """

    def delete_document(self, doc_id: str) -> None:
        with self.writing(doc_id) as write:
            write.delete()

    # -- items -------------------------------------------------------------------------------

    def read_base(self, doc_id: str) -> ItemTable:
        """The document's items as its last import (or compaction) wrote them, without the
        edits since: the rowset its row names, read in one statement (one version of it)."""
        query = (
            "SELECT b.ids, b.id_offsets, b.bodies, b.body_offsets, b.boxes, b.codec FROM bases b"
            " JOIN documents d ON d.id = b.doc_id AND d.rowset = b.rowset WHERE b.doc_id = ? ORDER BY b.chunk"
        )
        return table_of([decoded(row) for row in self._rows(query, doc_id)])

    def edits(self, doc_id: str, after: int = 0) -> list[Edit]:
        """The document's edits since its base, newer than version ``after``, oldest first: the
        last of each item, ``(item id, version, box, body)``; a deleted item's box and body are None."""
        rows = self._rows(
            "SELECT item_id, version, x0, y0, x1, y1, body FROM edits WHERE doc_id = ? AND version > ? ORDER BY version",
            doc_id,
            after,
        )
        return [edit_of(row) for row in rows]

    def last_edits(self, doc_id: str, upto: int, count: int) -> list[Edit]:
        """The ``count`` newest of the document's edits stored at version ``upto`` or before,
        newest first (what an edit file follows: ``editfile``). Cost: a pass over the
        document's edits, ``count`` of them kept."""
        rows = self._rows(
            "SELECT item_id, version, x0, y0, x1, y1, body FROM edits WHERE doc_id = ? AND version <= ?"
            " ORDER BY version DESC, item_id LIMIT ?",
            doc_id,
            upto,
            count,
        )
        return [edit_of(row) for row in rows]

    def read_items(self, doc_id: str, spill: Path | None = None) -> ItemTable:
        """The document's items as they stand, from its rows: its base with the edits since
        applied (a snapshot's base applies them itself: ``Snapshot.document_table``);
        ``spill``: where the merged bodies go (see ``ItemTable.merge``)."""
        base, edits = self.read_base(doc_id), self.edits(doc_id)
        if not edits:
            return base
        kept = [(item_id, box, body) for item_id, _, box, body in edits if body is not None]
        puts = ItemTable.of(
            [k[0] for k in kept], np.array([k[1] for k in kept], np.float64), [k[2] for k in kept]
        )
        return ItemTable.merge([base, puts], deleted=[e[0] for e in edits if e[3] is None], spill=spill)

    @abstractmethod
    def writing(self, doc_id: str) -> AbstractContextManager[Writing]:
        """A write transaction on the document (``with store.writing(doc) as write:``): every
        process's writers of it take turns.

        :raises NotFound: if there is no such document
        """

    def write_items(self, doc_id: str, table: ItemTable) -> int:
        """Make ``table`` the document's whole content in a transaction of its own; the version.
        Its base gets its name and snapshot file when the document is first opened."""
        with self.writing(doc_id) as write:
            version = write.bump()
            write.write_base(table, version, None, bounds_of(table.boxes))
        self.checkpoint()
        return version

    def stage_base(self, doc_id: str, table: ItemTable) -> Staged:
        """Write the base rows of ``table`` under a new rowset, unseen until a write points
        the document at them (``Writing.import_base``, ``Writing.compact_base``): each row
        encoded (on every core), then stored in a short transaction of its own that locks no
        document, so writers wait for one row's write at most, not the base's. Those written
        go again if it fails (or the sweep drops them: ``sweep_rows``)."""
        staged = Staged(new_rowset())
        try:
            pack = packer()
            for row in chunks(table):
                values = (doc_id, staged.rowset, *encoded(row, pack))
                with self._unlocked(doc_id) as write:
                    write._write_base_rows(iter([values]))
                staged.rows += 1
                self.checkpoint()  # each row's space handed back before the next's (SQLite's WAL)
        except BaseException:
            with contextlib.suppress(Exception):  # the store away, say: then the sweep drops them
                self.drop_rows(doc_id, staged.rowset)
            raise
        return staged

    def drop_rows(self, doc_id: str, rowset: int) -> int:
        """Delete the rows of ``rowset``, never its document's base's, a row a transaction (on
        SQLite, a row's blobs are read to be freed: all at once would hold every writer up);
        how many went."""
        dropped = 0
        while True:
            self._read_ahead(doc_id, rowset)
            with self._unlocked(doc_id) as write:
                if write._sql(DROP_ROW, doc_id, rowset, doc_id, doc_id, rowset).rowcount < 1:
                    return dropped
            dropped += 1
            self.checkpoint()  # as ``stage_base``'s rows

    def sweep_rows(self, grace: float = ROWS_GRACE_SECONDS) -> int:
        """Delete the rowsets of no document's base begun over ``grace`` seconds ago: left by
        a compaction killed before it pointed its document at them, or after (the old base's).
        A younger one may be a compaction's under way. The number of rows deleted."""
        stale = self._rows(
            "SELECT DISTINCT b.doc_id, b.rowset FROM bases b JOIN documents d ON d.id = b.doc_id"
            " WHERE b.rowset != d.rowset AND b.rowset < ?",
            _first_rowset_at(time.time() - grace),
        )
        return sum(self.drop_rows(doc_id, rowset) for doc_id, rowset in stale)

    @abstractmethod
    def _unlocked(self, doc_id: str) -> AbstractContextManager[Writing]:
        """A short write transaction that locks no document's row: only for rows that no read
        sees (``stage_base``, ``drop_rows``)."""

    def _read_ahead(self, doc_id: str, rowset: int) -> None:  # noqa: B027 (most engines: nothing)
        """Read what dropping the next row of ``rowset`` reads, before its write (SQLite
        reads a row's blobs to free their pages: from the disk, that held every writer up)."""

    def checkpoint(self) -> None:  # noqa: B027 (most engines have nothing to do)
        """Hand space back after a large write, where the engine keeps it (SQLite's WAL),
        holding no writer up unless it is past its bound."""

    # -- following other processes' writes ---------------------------------------------------

    @abstractmethod
    def changed(self) -> bool:
        """Whether another process may have committed something since the last call: a cheap
        look (no query), to call often from one thread. An engine whose signal can be missed
        (PostgreSQL's NOTIFY) also says yes now and then regardless, so a miss only delays."""

    def log_after(self, seq: int) -> list[Change]:
        """The change log's rows after ``seq``, in commit order."""
        rows = self._rows("SELECT seq, doc_id, version, kind FROM changes WHERE seq > ? ORDER BY seq", seq)
        return [Change(*row) for row in rows]

    def log_head(self) -> int:
        """The ``seq`` of the change log's last row (0: none)."""
        return int(self._rows("SELECT coalesce(max(seq), 0) FROM changes")[0][0])

    @abstractmethod
    def _rows(self, text: str, *args: object) -> list[tuple]:
        """The rows a read query answers, written with ``?`` placeholders, outside any write
        transaction (a reader never waits for a writer)."""

    def status(self) -> dict[str, Any]:
        """``{"store": engine, "reachable": bool}`` and, when it is not, why."""
        try:
            self.log_head()
        except StoreUnavailable as error:
            return {"store": self.engine, "reachable": False, "detail": error.message}
        return {"store": self.engine, "reachable": True}


def bounds_of(boxes: np.ndarray) -> list[float] | None:
    """A box containing every one of ``boxes``, or None: numpy's least x0 and y0 and greatest
    x1 and y1, to the sign of a zero. Read a step at a time, each step's pages handed back
    (mapped from a file, an import's boxes: 32 bytes an item at 1e8 items, the import's peak
    when read at once). Numpy's pick between 0.0 and -0.0 at a tie depends on how it splits
    its pass, so a side whose extreme is a zero of both signs is read again as one pass."""
    if not len(boxes):
        return None
    ends = [np.inf, np.inf, -np.inf, -np.inf]
    signs: list[set[bool]] = [set(), set(), set(), set()]  # of the zeros at each side's extreme
    for _, rows in in_steps(boxes):
        for k in range(4):
            column = rows[:, k]
            end = float(column.min() if k < 2 else column.max())
            ends[k] = min(ends[k], end) if k < 2 else max(ends[k], end)
            if end == 0.0:
                signs[k].update(np.unique(np.signbit(column[column == 0.0])).tolist())
    for k in range(4):
        if ends[k] == 0.0 and len(signs[k]) == 2:  # rare: a -0.0 in the document, at its edge
            try:
                ends[k] = float(boxes[:, k].min() if k < 2 else boxes[:, k].max())
            finally:
                release(boxes)
    return ends


def meta_of(row: tuple | list) -> dict[str, Any]:
    """A document's row as a dict (its columns in ``META``' order, bounds as JSON text)."""
    meta = dict(zip(META, row, strict=True))
    meta["bounds"] = json.loads(meta["bounds"]) if meta["bounds"] else None
    return meta


def bounds_json(bounds: Iterable[float] | None) -> str | None:
    return None if bounds is None else json.dumps([float(b) for b in bounds])


def chunks(table: ItemTable) -> Iterator[tuple[int, memoryview, bytes, memoryview, bytes]]:
    """The base rows of ``table``: ``(chunk, ids, id_offsets, bodies, body_offsets)``, the
    buffers views of the table's (a row is used before the next is made, not copied)."""
    bodies = table.bodies.unpacked()  # a table read or merged: in one buffer already
    offsets, start, chunk = bodies.offsets, 0, 0
    while start < len(table):
        most = int(np.searchsorted(offsets, offsets[start] + CHUNK_BYTES, side="right")) - 1
        stop = min(start + CHUNK, len(table), max(start + 1, most))
        yield chunk, *_slice(table.ids, start, stop), *_slice(bodies, start, stop)
        bodies.release()  # used: a spilled import's bodies go back to the page cache
        table.ids.release()  # ... and its ids
        start, chunk = stop, chunk + 1


def packer() -> Callable[[bytes | memoryview], bytes]:
    """zstd at ``ZSTD_LEVEL`` on every core, for one base's rows: a compressor's buffers (and
    its threads') are made once, not a row's worth faulted in again each row."""
    return zstandard.ZstdCompressor(level=ZSTD_LEVEL, threads=-1).compress


def encoded(row: tuple[int, memoryview, bytes, memoryview, bytes], pack: Callable[[Any], bytes]) -> tuple:
    """A base row as stored (but its document and rowset): each blob a zstd frame (``pack``,
    a ``packer``), offsets as the items' lengths, no boxes (each is in its item's JSON), then
    its codec (``LEAN``). JSON shrinks ~3x. The boxes were 30 B an item of a 10M board's 72."""
    chunk, ids, id_offsets, bodies, body_offsets = row
    return chunk, pack(ids), pack(_lengths(id_offsets)), pack(bodies), pack(_lengths(body_offsets)), b"", LEAN


def decoded(row: tuple) -> tuple[bytes, bytes, bytes, bytes, bytes]:
    """``(ids, id_offsets, bodies, body_offsets, boxes)`` of a stored base row: as ``encoded``
    made it, or as an earlier version wrote it (``RAW``, ``ZSTD``).

    :raises StoreError: if it cannot be read
    """
    *blobs, codec = row
    if codec == RAW:
        return tuple(bytes(b) for b in blobs)  # type: ignore[return-value]
    if codec not in (ZSTD, LEAN):
        raise StoreError(f"a base row of codec {codec}, which this version cannot read")
    unpack = zstandard.ZstdDecompressor().decompress
    ids, id_lengths, bodies, body_lengths = map(unpack, blobs[:4])
    offsets = _offsets(body_lengths)
    if codec == ZSTD:
        boxes = unpack(blobs[4])
    else:
        try:
            boxes = boxes_of(bodies, np.frombuffer(offsets, np.int64)[1:]).tobytes()
        except ValueError as error:
            raise StoreError(f"a base row's items cannot be read: {error}") from None
    return ids, _offsets(id_lengths), bodies, offsets, boxes


def _lengths(offsets: bytes) -> bytes:
    return np.diff(np.frombuffer(offsets, np.int64)).tobytes()


def _offsets(lengths: bytes) -> bytes:
    return np.concatenate(([0], np.cumsum(np.frombuffer(lengths, np.int64)))).astype(np.int64).tobytes()


def table_of(rows: list) -> ItemTable:
    """The item table of base rows ``(ids, id_offsets, bodies, body_offsets, boxes)``, in chunk order."""
    return ItemTable(
        Packed.concat(
            [Packed(bytes(r[0]), np.frombuffer(r[1], np.int64)) for r in rows] or [Packed(b"", _ZERO)]
        ),
        Packed.concat(
            [Packed(bytes(r[2]), np.frombuffer(r[3], np.int64)) for r in rows] or [Packed(b"", _ZERO)]
        ),
        np.concatenate([np.frombuffer(r[4], np.float64).reshape(-1, 4) for r in rows] or [np.empty((0, 4))]),
    )


def edit_of(row: tuple) -> Edit:
    """``(item_id, version, x0, y0, x1, y1, body)`` as an edit."""
    body = row[6]
    return (row[0], row[1], None if body is None else tuple(row[2:6]), None if body is None else bytes(body))


_ZERO = np.zeros(1, np.int64)


def _slice(packed: Packed, start: int, stop: int) -> tuple[memoryview, bytes]:
    """Items ``start:stop`` of ``packed`` as a view of its buffer and their offsets, rebased to 0."""
    lo, hi = int(packed.offsets[start]), int(packed.offsets[stop])
    return memoryview(packed.buffer)[lo:hi], (
        packed.offsets[start : stop + 1].astype(np.int64) - lo
    ).tobytes()
