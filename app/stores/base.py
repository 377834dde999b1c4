"""The one interface every store implements, and what the engines share.

A document is a base, its items as a few column blobs written by the last import, plus the
single-item edits since (the last of each item). Every write is one transaction on one
document, begun by ``writing(doc_id)``, which locks the document against every other writer
(another worker, another replica) until it commits or rolls back: a failed import rolls back
whole, so nothing half-written survives it, and a document's versions are gap-free.

Every committed write also appends a row to the change log, in the same transaction: which
document reached which version, and how (an import, an edit, a deletion). The log's ``seq``
orders rows as their transactions committed, so a process that follows the log from the last
``seq`` it saw (``log_after``) misses nothing, whenever it looks and however long it was away.
"""

from __future__ import annotations

import asyncio
import json
import os
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractAsyncContextManager, AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zstandard

from ..errors import ServiceError
from ..items import boxes_of
from ..table import Edit, ItemTable, Packed

__all__ = [
    "CHUNK",
    "CHUNK_BYTES",
    "Change",
    "Edit",
    "EncodedRows",
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
META = ("id", "name", "created", "version", "base_id", "base_version", "items", "bounds")
META_QUERY = f"SELECT {', '.join(META)} FROM documents"
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
        """Make ``table`` the document's whole content at ``version``, its base named ``base_id``."""
        self._sql(
            "UPDATE documents SET items = ?, bounds = ? WHERE id = ?",
            len(table),
            bounds_json(bounds),
            self._id,
        )
        self._replace_base((encoded(row) for row in chunks(table)), version, base_id)
        self._log(version, "import")

    def compact_base(self, rows: Iterable[tuple], version: int, base_id: str) -> None:
        """Make ``rows`` (``encoded``: ``EncodedRows``, say), the document's items as of
        ``version`` (some edited since, maybe, as their last edit left them), its base named
        ``base_id``: the edits since ``version`` stay, and the document's version, items and
        bounds do not change."""
        self._replace_base(rows, version, base_id)
        self._log(self.meta["version"], "compact")

    def _replace_base(self, rows: Iterable[tuple], version: int, base_id: str | None) -> None:
        """The ``encoded`` ``rows`` as the base at ``version``, without the edits up to it."""
        self._sql(
            "UPDATE documents SET base_id = ?, base_version = ? WHERE id = ?", base_id, version, self._id
        )
        self._sql("DELETE FROM bases WHERE doc_id = ?", self._id)
        self._sql("DELETE FROM edits WHERE doc_id = ? AND version <= ?", self._id, version)
        self._write_base_rows((self._id, *row) for row in rows)
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
        """Insert ``rows`` into ``bases``: ``(doc_id, chunk, ids, id_offsets, bodies, body_offsets,
        boxes, codec)``."""


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
        """The document's items as its last import wrote them, without the edits since."""
        query = "SELECT ids, id_offsets, bodies, body_offsets, boxes, codec FROM bases WHERE doc_id = ? ORDER BY chunk"
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

    def checkpoint(self) -> None:  # noqa: B027 (most engines have nothing to do)
        """Hand space back after a large write, where the engine keeps it (SQLite's WAL)."""

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
    """A box containing every one of ``boxes``, or None."""
    if not len(boxes):
        return None
    return [
        float(boxes[:, 0].min()),
        float(boxes[:, 1].min()),
        float(boxes[:, 2].max()),
        float(boxes[:, 3].max()),
    ]


def meta_of(row: tuple | list) -> dict[str, Any]:
    """A document's row as a dict (its columns in ``META``' order, bounds as JSON text)."""
    meta = dict(zip(META, row, strict=True))
    meta["bounds"] = json.loads(meta["bounds"]) if meta["bounds"] else None
    return meta


def bounds_json(bounds: Iterable[float] | None) -> str | None:
    return None if bounds is None else json.dumps([float(b) for b in bounds])


def chunks(table: ItemTable) -> Iterator[tuple[int, memoryview, bytes, memoryview, bytes, memoryview]]:
    """The base rows of ``table``: ``(chunk, ids, id_offsets, bodies, body_offsets, boxes)``,
    the buffers views of the table's (a row is used before the next is made, not copied)."""
    bodies = table.bodies.unpacked()  # a table read or merged: in one buffer already
    offsets, start, chunk = bodies.offsets, 0, 0
    while start < len(table):
        most = int(np.searchsorted(offsets, offsets[start] + CHUNK_BYTES, side="right")) - 1
        stop = min(start + CHUNK, len(table), max(start + 1, most))
        yield (
            chunk,
            *_slice(table.ids, start, stop),
            *_slice(bodies, start, stop),
            np.ascontiguousarray(table.boxes[start:stop]).data.cast("B"),
        )
        bodies.release()  # used: a spilled import's bodies go back to the page cache
        table.ids.release()  # ... and its ids
        start, chunk = stop, chunk + 1


class EncodedRows:
    """The base rows of ``table``, ``encoded`` ahead of the write that stores them, spooled to
    a file in ``directory`` (deleted when closed): that write then only copies their bytes. A
    compaction encodes them while it builds its base, outside the writers' turn."""

    def __init__(self, table: ItemTable, directory: Path) -> None:
        self._file = tempfile.TemporaryFile(dir=directory)  # noqa: SIM115 (closed by close())
        self._rows: list[tuple[int, list[tuple[int, int]], int]] = []  # chunk, its blobs' spans, codec
        at = 0
        for row in chunks(table):
            chunk, *blobs, codec = encoded(row)
            spans = []
            for blob in blobs:
                self._file.write(blob)
                spans.append((at, len(blob)))
                at += len(blob)
            self._rows.append((chunk, spans, codec))
        self._file.flush()

    def __iter__(self) -> Iterator[tuple]:
        """Each row as ``encoded`` made it, read back one at a time."""
        fd = self._file.fileno()
        for chunk, spans, codec in self._rows:
            yield (chunk, *(os.pread(fd, length, start) for start, length in spans), codec)

    def close(self) -> None:
        self._file.close()


def encoded(row: tuple[int, memoryview, bytes, memoryview, bytes, memoryview]) -> tuple:
    """A base row as stored: each blob a zstd frame, offsets as the items' lengths, no boxes
    (each is in its item's JSON), then its codec (``LEAN``). JSON shrinks ~3x; a frame is
    made on every core. The boxes were 30 B an item of a 10M board's 72."""
    chunk, ids, id_offsets, bodies, body_offsets, _ = row
    pack = zstandard.ZstdCompressor(level=ZSTD_LEVEL, threads=-1).compress
    return (
        chunk,
        pack(ids),
        pack(_lengths(id_offsets)),
        pack(bodies),
        pack(_lengths(body_offsets)),
        b"",
        LEAN,
    )


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
