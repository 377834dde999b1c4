"""The persistent store: SQLite (stdlib) in WAL mode under the data directory.

A document is a base, its items as a few column blobs written by the last import, plus a
table of the single-item edits since. Bulk imports (the common write) rewrite the base in one
transaction; loading a million items is reading blobs, not a million rows. Every write is one
``BEGIN IMMEDIATE`` transaction, which also makes the writers of every process (every worker)
take turns: a failed import rolls back whole, so nothing half-written survives it.

A document's row says which base it has (``base_id``, a name no other base ever had, and the
version that wrote it) and, for listing without opening anything, how many items it holds and
a box containing them all. Readers use a connection per thread; ``changed()`` tells, at the
cost of a look at SQLite's shared WAL index, whether another process committed anything.

Writers from the event loop wait for their turn there (``Store.turn``, first come first
served) and only then take a worker thread for the write itself: a long write (a large
import) keeps the writers queued behind it out of the thread pool that every reader needs.
A threading lock still guards the connection for callers off the event loop.
"""

from __future__ import annotations

import asyncio
import json
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .errors import Conflict, NotFound, StorageFull
from .table import ItemTable, Packed

__all__ = ["Store", "StoreError"]

FORMAT = 3  # PRAGMA user_version of the layout below
SCHEMA = """
CREATE TABLE IF NOT EXISTS documents (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    created REAL NOT NULL,
    version INTEGER NOT NULL DEFAULT 0,
    base_id TEXT,              -- names the base's snapshot file (NULL: none yet)
    base_version INTEGER NOT NULL DEFAULT 0,
    items INTEGER NOT NULL DEFAULT 0,
    bounds TEXT                -- JSON [x0, y0, x1, y1] containing every item, or NULL
);
CREATE TABLE IF NOT EXISTS bases (
    doc_id TEXT NOT NULL REFERENCES documents(id) ON DELETE CASCADE,
    chunk INTEGER NOT NULL,
    ids BLOB NOT NULL, id_offsets BLOB NOT NULL,
    bodies BLOB NOT NULL, body_offsets BLOB NOT NULL,
    boxes BLOB NOT NULL,
    PRIMARY KEY (doc_id, chunk)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS edits (
    doc_id TEXT NOT NULL REFERENCES documents(id) ON DELETE CASCADE,
    item_id TEXT NOT NULL,
    version INTEGER NOT NULL,
    x0 REAL, y0 REAL, x1 REAL, y1 REAL,
    body BLOB,  -- NULL: deleted
    PRIMARY KEY (doc_id, item_id)
) WITHOUT ROWID;
"""
CHUNK = 1 << 18  # items per base row: blobs stay far below SQLite's 1 GB limit
MIGRATIONS = {  # from the layout of that version to the next
    2: """
    ALTER TABLE documents ADD COLUMN base_id TEXT;
    ALTER TABLE documents ADD COLUMN base_version INTEGER NOT NULL DEFAULT 0;
    ALTER TABLE documents ADD COLUMN items INTEGER NOT NULL DEFAULT 0;
    ALTER TABLE documents ADD COLUMN bounds TEXT;
    """,
}
BUSY_SECONDS = 60.0  # a writer waits this long for another process's write (a long import) to end
_META = "SELECT id, name, created, version, base_id, base_version, items, bounds FROM documents"

_EDIT = """
INSERT INTO edits VALUES (?, ?, ?, ?, ?, ?, ?, ?)
ON CONFLICT (doc_id, item_id) DO UPDATE SET version = excluded.version,
    x0 = excluded.x0, y0 = excluded.y0, x1 = excluded.x1, y1 = excluded.y1, body = excluded.body
"""


class StoreError(RuntimeError):
    """The data directory cannot be used as it is; the message says what to do."""


class Store:
    """Documents and their items on disk. Methods raise NotFound for an unknown document."""

    def __init__(self, data_dir: Path) -> None:
        data_dir.mkdir(parents=True, exist_ok=True)
        self.path = data_dir / "vantage.sqlite3"
        self._db = self._connect()  # the writer's
        self._db.execute("PRAGMA journal_mode = WAL")
        with self._transaction():  # one process lays out or migrates the store; others wait
            found = self._db.execute("PRAGMA user_version").fetchone()[0]
            tables = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            if tables and found != FORMAT:
                if found > FORMAT or any(step not in MIGRATIONS for step in range(found, FORMAT)):
                    raise StoreError(
                        f"{self.path} holds a store of format {found}, which this version (format "
                        f"{FORMAT}) cannot read: move it away or point VANTAGE_DATA_DIR elsewhere"
                    )
                for step in range(found, FORMAT):
                    for statement in filter(str.strip, MIGRATIONS[step].split(";")):
                        self._db.execute(statement)
            for statement in filter(str.strip, SCHEMA.split(";")):
                self._db.execute(statement)
            self._db.execute(f"PRAGMA user_version = {FORMAT}")
        self._lock = threading.Lock()
        self._readers = threading.local()
        self._watch = self._connect()  # only changed() uses it: data_version is per connection
        self._seen = self._data_version()
        # The event loop's queue of writers: ``async with store.turn:`` before taking a thread.
        self.turn = asyncio.Lock()

    def close(self) -> None:
        self._db.close()
        self._watch.close()

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=BUSY_SECONDS)
        db.execute("PRAGMA synchronous = NORMAL")  # durable at checkpoints; WAL keeps it atomic
        db.execute("PRAGMA foreign_keys = ON")
        return db

    def _reader(self) -> sqlite3.Connection:
        """This thread's connection for reads: in WAL mode they never wait for a writer."""
        db = getattr(self._readers, "db", None)
        if db is None:
            db = self._readers.db = self._connect()
        return db

    def _data_version(self) -> int:
        return int(self._watch.execute("PRAGMA data_version").fetchone()[0])

    def changed(self) -> bool:
        """Whether another connection (another process) committed anything since the last call.
        Cost: a look at SQLite's shared WAL index, no disk read. Call it from one thread."""
        version = self._data_version()
        seen, self._seen = self._seen, version
        return version != seen

    # -- documents -----------------------------------------------------------------------------

    def create_document(self, name: str, max_documents: int | None = None) -> dict[str, Any]:
        """A new, empty document.

        :raises Conflict: if the store holds ``max_documents`` already
        """
        doc = {"id": uuid.uuid4().hex[:12], "name": name, "created": time.time()}
        with self._lock, self._transaction():
            held = self._db.execute("SELECT count(*) FROM documents").fetchone()[0]
            if max_documents is not None and held >= max_documents:
                raise Conflict(
                    f"the store holds {held} documents, the most it may (VANTAGE_MAX_DOCUMENTS): delete one first"
                )
            self._db.execute("INSERT INTO documents (id, name, created) VALUES (:id, :name, :created)", doc)
        return self.document(doc["id"])

    def documents(self) -> list[dict[str, Any]]:
        """Every document's row, oldest first."""
        return [_meta(r) for r in self._reader().execute(_META + " ORDER BY created").fetchall()]

    def document(self, doc_id: str) -> dict[str, Any]:
        """One document's row: id, name, created, version, base_id, base_version, items, bounds.

        :raises NotFound: if there is no such document
        """
        row = self._reader().execute(_META + " WHERE id = ?", (doc_id,)).fetchone()
        if row is None:
            raise NotFound(f"document {doc_id!r} not found")
        return _meta(row)

    def heads(self, doc_ids: list[str]) -> dict[str, tuple[int, str | None]]:
        """``{id: (version, base_id)}`` of those of ``doc_ids`` that exist."""
        marks = ",".join("?" * len(doc_ids))
        rows = self._reader().execute(
            f"SELECT id, version, base_id FROM documents WHERE id IN ({marks})", doc_ids
        )
        return {r[0]: (r[1], r[2]) for r in rows}

    def delete_document(self, doc_id: str) -> None:
        with self.writing():
            if self._db.execute("DELETE FROM documents WHERE id = ?", (doc_id,)).rowcount == 0:
                raise NotFound(f"document {doc_id!r} not found")

    # -- items ---------------------------------------------------------------------------------

    def read_items(self, doc_id: str) -> ItemTable:
        """The document's items as they stand: its base with the edits since applied."""
        base, edits = self.read_base(doc_id), self.edits(doc_id)
        if not edits:
            return base
        kept = [e for e in edits if e[3] is not None]
        puts = ItemTable.of(
            [e[0] for e in kept], np.array([e[2] for e in kept], np.float64), [e[3] for e in kept]
        )
        return ItemTable.merge([base, puts], deleted=[e[0] for e in edits if e[3] is None])

    def edits(self, doc_id: str, after: int = 0) -> list[tuple[str, int, tuple | None, bytes | None]]:
        """The document's edits since its base, newer than version ``after``, oldest first: the
        last of each item, ``(item id, version, box, body)``; a deleted item's box and body are None."""
        rows = self._reader().execute(
            "SELECT item_id, version, x0, y0, x1, y1, body FROM edits WHERE doc_id = ? AND version > ? ORDER BY version",
            (doc_id, after),
        )
        return [(r[0], r[1], None if r[6] is None else r[2:6], r[6]) for r in rows]

    def read_base(self, doc_id: str) -> ItemTable:
        """The document's items as its last import wrote them, without the edits since."""
        chunks = (
            self._reader()
            .execute(
                "SELECT ids, id_offsets, bodies, body_offsets, boxes FROM bases WHERE doc_id = ? ORDER BY chunk",
                (doc_id,),
            )
            .fetchall()
        )
        base = ItemTable(
            Packed.concat(
                [Packed(c[0], np.frombuffer(c[1], np.int64)) for c in chunks] or [Packed(b"", _ZERO)]
            ),
            Packed.concat(
                [Packed(c[2], np.frombuffer(c[3], np.int64)) for c in chunks] or [Packed(b"", _ZERO)]
            ),
            np.concatenate(
                [np.frombuffer(c[4], np.float64).reshape(-1, 4) for c in chunks] or [np.empty((0, 4))]
            ),
        )
        return base

    def writing(self) -> _Transaction:
        """A write transaction (``with store.writing():``): every process's writers take turns;
        the ``write_*`` methods below run inside one."""
        self._lock.acquire()
        return _Transaction(self._db, self._lock.release)

    def set_base_id(self, doc_id: str, base_id: str) -> None:
        """Name a document's base that had no name (a store laid out before base ids)."""
        with self.writing():
            self._db.execute(
                "UPDATE documents SET base_id = ? WHERE id = ? AND base_id IS NULL", (base_id, doc_id)
            )

    def bump(self, doc_id: str) -> int:
        """The document's next version (in a ``writing()`` transaction)."""
        return self._bump(doc_id)

    def write_base(
        self, doc_id: str, table: ItemTable, version: int, base_id: str | None, bounds: object
    ) -> None:
        """Make ``table`` the document's whole content at ``version``, its base named ``base_id``
        (in a ``writing()`` transaction, whose version it is)."""
        self._db.execute(
            "UPDATE documents SET base_id = ?, base_version = ?, items = ?, bounds = ? WHERE id = ?",
            (base_id, version, len(table), _json(bounds), doc_id),
        )
        self._db.execute("DELETE FROM bases WHERE doc_id = ?", (doc_id,))
        self._db.execute("DELETE FROM edits WHERE doc_id = ?", (doc_id,))
        for chunk, start in enumerate(range(0, len(table), CHUNK)):
            stop = min(start + CHUNK, len(table))
            ids, id_offsets = _slice(table.ids, start, stop)
            bodies, body_offsets = _slice(table.bodies, start, stop)
            boxes = table.boxes[start:stop].tobytes()
            self._db.execute(
                "INSERT INTO bases VALUES (?, ?, ?, ?, ?, ?, ?)",
                (doc_id, chunk, ids, id_offsets, bodies, body_offsets, boxes),
            )

    def write_items(self, doc_id: str, table: ItemTable) -> int:
        """Make ``table`` the document's whole content in a transaction of its own; the version.
        Its base gets its name and snapshot file when the document is first opened."""
        with self.writing():
            version = self.bump(doc_id)
            boxes = table.boxes
            bounds = (
                (boxes[:, 0].min(), boxes[:, 1].min(), boxes[:, 2].max(), boxes[:, 3].max())
                if len(boxes)
                else None
            )
            self.write_base(
                doc_id, table, version, None, None if bounds is None else [float(b) for b in bounds]
            )
        self.checkpoint()
        return version

    def checkpoint(self) -> None:
        """Hand the WAL's pages back (after a large import, which would leave its size on disk)."""
        with self._lock:
            self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")

    def write_edits(
        self,
        doc_id: str,
        version: int,
        edits: list[tuple[str, tuple | None, bytes | None]],
        items: int,
        bounds: object,
    ) -> None:
        """Store ``edits``, ``(item id, box, body)`` each at ``version`` (box and body None:
        deleted), and the document's item count and bounds after them (in a ``writing()``
        transaction)."""
        self._db.executemany(
            _EDIT, [(doc_id, item_id, version, *(box or (None,) * 4), body) for item_id, box, body in edits]
        )
        self._db.execute(
            "UPDATE documents SET items = ?, bounds = ? WHERE id = ?", (items, _json(bounds), doc_id)
        )

    # -- internals -----------------------------------------------------------------------------

    def _bump(self, doc_id: str) -> int:
        row = self._db.execute(
            "UPDATE documents SET version = version + 1 WHERE id = ? RETURNING version", (doc_id,)
        ).fetchone()
        if row is None:
            raise NotFound(f"document {doc_id!r} not found")
        return int(row[0])

    def _transaction(self) -> _Transaction:
        return _Transaction(self._db)


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT, or ROLLBACK on any exception; a full disk (or database size
    limit) becomes ``StorageFull``; ``done`` is called at the end either way."""

    def __init__(self, db: sqlite3.Connection, done: Callable[[], object] = lambda: None) -> None:
        self._db, self._done = db, done

    def __enter__(self) -> None:
        try:
            self._db.execute("BEGIN IMMEDIATE")
        except BaseException:
            self._done()
            raise

    def __exit__(self, kind: object, error: object, trace: object) -> None:
        try:
            self._end(kind, error)
        finally:
            self._done()

    def _end(self, kind: object, error: object) -> None:
        if kind is not None:
            if self._db.in_transaction:  # SQLite rolls some failures (a full disk) back itself
                self._db.execute("ROLLBACK")
            _raise_if_full(error)
            return  # the error goes on as it is
        try:
            self._db.execute("COMMIT")
        except sqlite3.OperationalError as failed:  # a commit can fail too
            if self._db.in_transaction:
                self._db.execute("ROLLBACK")
            _raise_if_full(failed)
            raise


def _raise_if_full(error: object) -> None:
    if isinstance(error, sqlite3.OperationalError) and error.sqlite_errorcode == sqlite3.SQLITE_FULL:
        raise StorageFull(f"the store is full ({error}): nothing was written; free some space") from error


_ZERO = np.zeros(1, np.int64)


def _meta(row: tuple) -> dict[str, Any]:
    names = ("id", "name", "created", "version", "base_id", "base_version", "items", "bounds")
    meta = dict(zip(names, row, strict=True))
    meta["bounds"] = json.loads(meta["bounds"]) if meta["bounds"] else None
    return meta


def _json(bounds: object) -> str | None:
    return None if bounds is None else json.dumps(list(bounds))


def _slice(packed: Packed, start: int, stop: int) -> tuple[bytes, bytes]:
    """Items ``start:stop`` of ``packed`` as a buffer and its offsets, rebased to 0."""
    lo, hi = packed.offsets[start], packed.offsets[stop]
    return packed.buffer[lo:hi], (packed.offsets[start : stop + 1] - lo).tobytes()
