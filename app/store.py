"""The persistent store: SQLite (stdlib) in WAL mode under the data directory.

A document is a base, its items as a few column blobs written by the last import, plus a
table of the single-item edits since. Bulk imports (the common write) rewrite the base in one
transaction; loading a million items is reading blobs, not a million rows. One connection,
one writer at a time, every write in one transaction: a failed import rolls back whole, so
nothing half-written survives it.

Writers from the event loop wait for their turn there (``Store.turn``, first come first
served) and only then take a worker thread for the write itself: a long write (a large
import) keeps the writers queued behind it out of the thread pool that every reader needs.
A threading lock still guards the connection for callers off the event loop.
"""

import asyncio
import sqlite3
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from .errors import NotFound, StorageFull
from .table import ItemTable, Packed

__all__ = ["Store", "StoreError"]

FORMAT = 2  # PRAGMA user_version of the layout below
SCHEMA = """
CREATE TABLE IF NOT EXISTS documents (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    created REAL NOT NULL,
    version INTEGER NOT NULL DEFAULT 0
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
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode = WAL")
        self._db.execute("PRAGMA synchronous = NORMAL")  # durable at checkpoints; WAL keeps it atomic
        self._db.execute("PRAGMA foreign_keys = ON")
        found = self._db.execute("PRAGMA user_version").fetchone()[0]
        tables = {row[0] for row in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if found != FORMAT and tables:
            self._db.close()
            raise StoreError(
                f"{self.path} holds an older store format ({found}, this version reads {FORMAT}): "
                "move it away or point VANTAGE_DATA_DIR elsewhere"
            )
        self._db.executescript(SCHEMA)
        self._db.execute(f"PRAGMA user_version = {FORMAT}")
        self._lock = threading.Lock()
        # The event loop's queue of writers: ``async with store.turn:`` before taking a thread.
        self.turn = asyncio.Lock()

    def close(self) -> None:
        self._db.close()

    # -- documents -----------------------------------------------------------------------------

    def create_document(self, name: str) -> dict[str, Any]:
        doc = {"id": uuid.uuid4().hex[:12], "name": name, "created": time.time(), "version": 0}
        with self._lock:
            self._db.execute("INSERT INTO documents VALUES (:id, :name, :created, :version)", doc)
        return doc

    def documents(self) -> list[dict[str, Any]]:
        rows = self._db.execute(
            "SELECT id, name, created, version FROM documents ORDER BY created"
        ).fetchall()
        return [{"id": r[0], "name": r[1], "created": r[2], "version": r[3]} for r in rows]

    def delete_document(self, doc_id: str) -> None:
        with self._lock, self._transaction():
            if self._db.execute("DELETE FROM documents WHERE id = ?", (doc_id,)).rowcount == 0:
                raise NotFound(f"document {doc_id!r} not found")

    # -- items ---------------------------------------------------------------------------------

    def read_items(self, doc_id: str) -> ItemTable:
        """The document's items as they stand: its base with the edits since applied."""
        chunks = self._db.execute(
            "SELECT ids, id_offsets, bodies, body_offsets, boxes FROM bases WHERE doc_id = ? ORDER BY chunk",
            (doc_id,),
        ).fetchall()
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
        edits = self._db.execute(
            "SELECT item_id, x0, y0, x1, y1, body FROM edits WHERE doc_id = ? ORDER BY version", (doc_id,)
        ).fetchall()
        if not edits:
            return base
        kept = [e for e in edits if e[5] is not None]
        puts = ItemTable.of(
            [e[0] for e in kept], np.array([e[1:5] for e in kept], np.float64), [e[5] for e in kept]
        )
        return ItemTable.merge([base, puts], deleted=[e[0] for e in edits if e[5] is None])

    def write_items(self, doc_id: str, table: ItemTable) -> int:
        """Make ``table`` the document's whole content in one transaction; the new version."""
        with self._lock:
            with self._transaction():
                version = self._bump(doc_id)
                self._db.execute("DELETE FROM bases WHERE doc_id = ?", (doc_id,))
                self._db.execute("DELETE FROM edits WHERE doc_id = ?", (doc_id,))
                for chunk, start in enumerate(range(0, len(table), CHUNK)):
                    stop = min(start + CHUNK, len(table))
                    ids, id_offsets = _slice(table.ids, start, stop)
                    bodies, body_offsets = _slice(table.bodies, start, stop)
                    self._db.execute(
                        "INSERT INTO bases VALUES (?, ?, ?, ?, ?, ?, ?)",
                        (
                            doc_id,
                            chunk,
                            ids,
                            id_offsets,
                            bodies,
                            body_offsets,
                            table.boxes[start:stop].tobytes(),
                        ),
                    )
            # Hand the WAL's pages back: a large import would otherwise leave its size on disk for good.
            self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        return version

    def put_item(self, doc_id: str, item_id: str, box: tuple[float, ...], body: bytes) -> int:
        """Insert or replace one item; the new version."""
        with self._lock, self._transaction():
            version = self._bump(doc_id)
            self._db.execute(_EDIT, (doc_id, item_id, version, *box, body))
        return version

    def delete_item(self, doc_id: str, item_id: str) -> int:
        """Delete one item (the caller knows it exists); the new version."""
        with self._lock, self._transaction():
            version = self._bump(doc_id)
            self._db.execute(_EDIT, (doc_id, item_id, version, None, None, None, None, None))
        return version

    # -- internals -----------------------------------------------------------------------------

    def _bump(self, doc_id: str) -> int:
        row = self._db.execute(
            "UPDATE documents SET version = version + 1 WHERE id = ? RETURNING version", (doc_id,)
        ).fetchone()
        if row is None:
            raise NotFound(f"document {doc_id!r} not found")
        return int(row[0])

    def _transaction(self) -> "_Transaction":
        return _Transaction(self._db)


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT, or ROLLBACK on any exception; a full disk (or database size
    limit) becomes ``StorageFull``."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __enter__(self) -> None:
        self._db.execute("BEGIN IMMEDIATE")

    def __exit__(self, kind: object, error: object, trace: object) -> None:
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


def _slice(packed: Packed, start: int, stop: int) -> tuple[bytes, bytes]:
    """Items ``start:stop`` of ``packed`` as a buffer and its offsets, rebased to 0."""
    lo, hi = packed.offsets[start], packed.offsets[stop]
    return packed.buffer[lo:hi], (packed.offsets[start : stop + 1] - lo).tobytes()
