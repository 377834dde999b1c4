"""The persistent store: SQLite (stdlib) in WAL mode under the data directory.

One connection, one writer at a time (a lock), every write in one transaction: a failed import
rolls back whole, so nothing half-written survives it.
"""

import sqlite3
import threading
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

__all__ = ["Store"]

SCHEMA = """
CREATE TABLE IF NOT EXISTS documents (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    created REAL NOT NULL,
    version INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS items (
    doc_id TEXT NOT NULL REFERENCES documents(id) ON DELETE CASCADE,
    item_id TEXT NOT NULL,
    x0 REAL NOT NULL, y0 REAL NOT NULL, x1 REAL NOT NULL, y1 REAL NOT NULL,
    kind TEXT NOT NULL,
    z INTEGER NOT NULL,
    data BLOB,
    PRIMARY KEY (doc_id, item_id)
) WITHOUT ROWID;
"""

_UPSERT = """
INSERT INTO items (doc_id, item_id, x0, y0, x1, y1, kind, z, data) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)
ON CONFLICT (doc_id, item_id) DO UPDATE SET
    x0 = excluded.x0, y0 = excluded.y0, x1 = excluded.x1, y1 = excluded.y1,
    kind = excluded.kind, z = excluded.z, data = excluded.data
"""
_BATCH = 5_000


class Store:
    """Documents and their items on disk. Methods raise KeyError for an unknown document."""

    def __init__(self, data_dir: Path) -> None:
        data_dir.mkdir(parents=True, exist_ok=True)
        self.path = data_dir / "vantage.sqlite3"
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode = WAL")
        self._db.execute("PRAGMA synchronous = NORMAL")  # durable at checkpoints; WAL keeps it atomic
        self._db.execute("PRAGMA foreign_keys = ON")
        self._db.executescript(SCHEMA)
        self._lock = threading.Lock()

    def close(self) -> None:
        self._db.close()

    # -- documents -----------------------------------------------------------------------------

    def create_document(self, name: str) -> dict[str, Any]:
        doc = {"id": uuid.uuid4().hex[:12], "name": name, "created": time.time(), "version": 0}
        with self._lock:
            self._db.execute("INSERT INTO documents VALUES (:id, :name, :created, :version)", doc)
        return doc

    def documents(self) -> list[dict[str, Any]]:
        rows = self._db.execute("SELECT id, name, created, version FROM documents ORDER BY created").fetchall()
        return [{"id": r[0], "name": r[1], "created": r[2], "version": r[3]} for r in rows]

    def delete_document(self, doc_id: str) -> None:
        with self._lock, self._transaction():
            if self._db.execute("DELETE FROM documents WHERE id = ?", (doc_id,)).rowcount == 0:
                raise KeyError(doc_id)

    # -- items ---------------------------------------------------------------------------------

    def items(self, doc_id: str) -> Iterator[tuple]:
        """Rows ``(item_id, x0, y0, x1, y1, kind, z, data)``, in id order."""
        cursor = self._db.execute(
            "SELECT item_id, x0, y0, x1, y1, kind, z, data FROM items WHERE doc_id = ? ORDER BY item_id",
            (doc_id,),
        )
        while batch := cursor.fetchmany(_BATCH):
            yield from batch

    def import_items(self, doc_id: str, items: Iterable[dict[str, Any]]) -> tuple[int, int]:
        """Upsert every item in one transaction; ``(count, new version)``. If iterating ``items``
        raises, nothing is stored and the exception propagates."""
        count = 0
        with self._lock, self._transaction():
            version = self._bump(doc_id)
            batch: list[tuple] = []
            for item in items:
                batch.append(_row(doc_id, item))
                if len(batch) == _BATCH:
                    self._db.executemany(_UPSERT, batch)
                    count += len(batch)
                    batch.clear()
            self._db.executemany(_UPSERT, batch)
            count += len(batch)
        return count, version

    def put_item(self, doc_id: str, item: dict[str, Any]) -> int:
        """Insert or replace one item; the new version."""
        with self._lock, self._transaction():
            version = self._bump(doc_id)
            self._db.execute(_UPSERT, _row(doc_id, item))
        return version

    def delete_item(self, doc_id: str, item_id: str) -> int:
        """Delete one item; the new version. KeyError if either is unknown."""
        with self._lock, self._transaction():
            version = self._bump(doc_id)
            deleted = self._db.execute("DELETE FROM items WHERE doc_id = ? AND item_id = ?", (doc_id, item_id))
            if deleted.rowcount == 0:
                raise KeyError(item_id)
        return version

    # -- internals -----------------------------------------------------------------------------

    def _bump(self, doc_id: str) -> int:
        row = self._db.execute(
            "UPDATE documents SET version = version + 1 WHERE id = ? RETURNING version", (doc_id,)
        ).fetchone()
        if row is None:
            raise KeyError(doc_id)
        return int(row[0])

    def _transaction(self) -> "_Transaction":
        return _Transaction(self._db)


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT, or ROLLBACK on any exception."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __enter__(self) -> None:
        self._db.execute("BEGIN IMMEDIATE")

    def __exit__(self, kind: object, error: object, trace: object) -> None:
        self._db.execute("COMMIT" if kind is None else "ROLLBACK")


def _row(doc_id: str, item: dict[str, Any]) -> tuple:
    return (doc_id, item["id"], item["x0"], item["y0"], item["x1"], item["y1"], item["kind"], item["z"], item["data"])
