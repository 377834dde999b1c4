"""The embedded store: SQLite (stdlib) in WAL mode under the data directory, the default.

Every write is one ``BEGIN IMMEDIATE`` transaction, which makes the writers of every process
(every worker) take turns; the change log's ``seq`` is therefore commit-ordered as it is. Readers
use a connection per thread and never wait for a writer; ``changed()`` tells, at the cost of a
look at SQLite's shared WAL index, whether another process committed anything.
A threading lock guards the writer's connection for the threads of one process.

No commit copies the WAL into the database itself (SQLite's autocheckpoint is off): it would
fall to whichever commit crossed 1000 pages, another process's import rows and all, and with
them an fsync, which on a disk busy writing a snapshot file took over a second: an edit's
wait. A thread of each store, ``_Checkpointer``, copies it beside the writers instead.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ..errors import Conflict, NotFound, StorageFull
from .base import (
    META_QUERY,
    Store,
    StoreError,
    Writing,
    meta_of,
)

__all__ = ["SQLiteStore"]

FORMAT = 6  # PRAGMA user_version of the layout below
WAL_LIMIT_BYTES = 64 << 20  # the WAL is cut back to this when it starts over (journal_size_limit)
CHECKPOINT_PAUSE = 0.25  # seconds between two of the checkpointer's copies, while commits come
BASES = """
CREATE TABLE IF NOT EXISTS {name} (
    doc_id TEXT NOT NULL REFERENCES documents(id) ON DELETE CASCADE,
    rowset INTEGER NOT NULL DEFAULT 0,  -- the base's when the document's row names it (base.py)
    chunk INTEGER NOT NULL,
    ids BLOB NOT NULL, id_offsets BLOB NOT NULL,
    bodies BLOB NOT NULL, body_offsets BLOB NOT NULL,
    boxes BLOB NOT NULL,
    codec INTEGER NOT NULL DEFAULT 0,  -- 0: the blobs as they are, 1: zstd frames (stores/base.py)
    PRIMARY KEY (doc_id, rowset, chunk)
) WITHOUT ROWID
"""
SCHEMA = f"""
CREATE TABLE IF NOT EXISTS documents (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    created REAL NOT NULL,
    version INTEGER NOT NULL DEFAULT 0,
    base_id TEXT,              -- names the base's snapshot file (NULL: none yet)
    base_version INTEGER NOT NULL DEFAULT 0,
    items INTEGER NOT NULL DEFAULT 0,
    bounds TEXT,               -- JSON [x0, y0, x1, y1] containing every item, or NULL
    rowset INTEGER NOT NULL DEFAULT 0  -- the rows of ``bases`` that are its base
);
{BASES.format(name="bases")};
CREATE TABLE IF NOT EXISTS edits (
    doc_id TEXT NOT NULL REFERENCES documents(id) ON DELETE CASCADE,
    item_id TEXT NOT NULL,
    version INTEGER NOT NULL,
    x0 REAL, y0 REAL, x1 REAL, y1 REAL,
    body BLOB,  -- NULL: deleted
    PRIMARY KEY (doc_id, item_id)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS changes (  -- outlives its document: followers learn of a deletion
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    doc_id TEXT NOT NULL,
    version INTEGER NOT NULL,
    kind TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS changes_of_document ON changes (doc_id, version);
"""
COLUMNS = "doc_id, rowset, chunk, ids, id_offsets, bodies, body_offsets, boxes, codec"
MIGRATIONS = {  # from the layout of that version to the next (SCHEMA then adds new tables)
    2: """
    ALTER TABLE documents ADD COLUMN base_id TEXT;
    ALTER TABLE documents ADD COLUMN base_version INTEGER NOT NULL DEFAULT 0;
    ALTER TABLE documents ADD COLUMN items INTEGER NOT NULL DEFAULT 0;
    ALTER TABLE documents ADD COLUMN bounds TEXT;
    """,
    3: "",  # the change log
    4: "ALTER TABLE bases ADD COLUMN codec INTEGER NOT NULL DEFAULT 0",  # rows written before: raw
    # Rowsets: each base's rows under a number the document names (a new primary key: a copy)
    5: f"""
    ALTER TABLE documents ADD COLUMN rowset INTEGER NOT NULL DEFAULT 0;
    {BASES.format(name="bases_6")};
    INSERT INTO bases_6 ({COLUMNS}) SELECT {COLUMNS.replace("rowset", "0")} FROM bases;
    DROP TABLE bases;
    ALTER TABLE bases_6 RENAME TO bases
    """,
}
BUSY_SECONDS = 60.0  # a writer waits this long for another process's write (a long import) to end


class SQLiteStore(Store):
    engine = "sqlite"

    def __init__(self, data_dir: Path) -> None:
        super().__init__()
        data_dir.mkdir(parents=True, exist_ok=True)
        self.path = data_dir / "vantage.sqlite3"
        self._db = self._connect()  # the writer's
        self._db.execute("PRAGMA journal_mode = WAL")
        self._checkpointer = _Checkpointer(self._connect())
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

    def close(self) -> None:
        self._checkpointer.close()
        self._db.close()
        self._watch.close()

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=BUSY_SECONDS)
        db.execute("PRAGMA synchronous = NORMAL")  # durable at checkpoints; WAL keeps it atomic
        db.execute("PRAGMA foreign_keys = ON")
        db.execute("PRAGMA wal_autocheckpoint = 0")  # the checkpointer's work, never a commit's
        # A freed page is not zeroed (as builds with SECURE_DELETE do): dropping an old base's
        # rows wrote every page of them to the WAL again, and the writers then waited for its copy.
        db.execute("PRAGMA secure_delete = FAST")
        db.execute(f"PRAGMA journal_size_limit = {WAL_LIMIT_BYTES}")
        return db

    def _reader(self) -> sqlite3.Connection:
        """This thread's connection for reads: in WAL mode they never wait for a writer."""
        db = getattr(self._readers, "db", None)
        if db is None:
            db = self._readers.db = self._connect()
        return db

    def _rows(self, text: str, *args: object) -> list[tuple]:
        return self._reader().execute(text, args).fetchall()

    def _data_version(self) -> int:
        return int(self._watch.execute("PRAGMA data_version").fetchone()[0])

    def changed(self) -> bool:
        """Cost: a look at SQLite's shared WAL index, no disk read."""
        version = self._data_version()
        seen, self._seen = self._seen, version
        return version != seen

    # -- documents -----------------------------------------------------------------------------

    def create_document(self, name: str, max_documents: int | None = None) -> dict[str, Any]:
        doc_id = uuid.uuid4().hex[:12]
        doc = {"id": doc_id, "name": name, "created": time.time()}
        with self._lock, self._transaction():
            held = self._db.execute("SELECT count(*) FROM documents").fetchone()[0]
            if max_documents is not None and held >= max_documents:
                raise Conflict(
                    f"the store holds {held} documents, the most it may (VANTAGE_MAX_DOCUMENTS): delete one first"
                )
            self._db.execute("INSERT INTO documents (id, name, created) VALUES (:id, :name, :created)", doc)
        return self.document(doc_id)

    def document(self, doc_id: str) -> dict[str, Any]:
        return _document(self._reader(), doc_id)

    # -- items ---------------------------------------------------------------------------------

    @contextmanager
    def writing(self, doc_id: str) -> Iterator[Writing]:
        with self._lock, self._transaction():
            yield _SQLiteWriting(self._db, _document(self._db, doc_id))

    @contextmanager
    def _unlocked(self, doc_id: str) -> Iterator[Writing]:
        with self._lock, self._transaction():  # SQLite locks the whole store: for one row's write
            yield _SQLiteWriting(self._db, {"id": doc_id})

    def _read_ahead(self, doc_id: str, rowset: int) -> None:
        self._rows(
            "SELECT ids, id_offsets, bodies, body_offsets, boxes FROM bases"
            " WHERE doc_id = ? AND rowset = ? ORDER BY chunk LIMIT 1",
            doc_id,
            rowset,
        )

    def checkpoint(self) -> None:
        """Copy the WAL into the database now, holding no writer up (after a large write: a
        staged row, paced so, or an import); if it is still past ``WAL_LIMIT_BYTES`` (an
        import in one write), truncate it, which every writer waits for."""
        self._checkpointer.copy()
        with contextlib.suppress(FileNotFoundError):
            if os.stat(f"{self.path}-wal").st_size <= WAL_LIMIT_BYTES:
                return
        with self._lock:
            for _ in range(100):  # busy while a checkpointer (this store's, say) copies: it ends soon
                if self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()[0] == 0:
                    return
                time.sleep(0.01)

    @contextmanager
    def _transaction(self) -> Iterator[None]:
        """BEGIN IMMEDIATE ... COMMIT, or ROLLBACK on any exception; a full disk (or database
        size limit) becomes ``StorageFull``."""
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield
        except BaseException as error:
            if self._db.in_transaction:  # SQLite rolls some failures (a full disk) back itself
                self._db.execute("ROLLBACK")
            _raise_if_full(error)
            raise
        try:
            self._db.execute("COMMIT")
        except sqlite3.OperationalError as failed:  # a commit can fail too
            if self._db.in_transaction:
                self._db.execute("ROLLBACK")
            _raise_if_full(failed)
            raise
        self._checkpointer.poke()


class _Checkpointer:
    """A thread that copies the WAL into the database (a PASSIVE checkpoint: no writer or
    reader waits for it) once a commit pokes it, at most every ``CHECKPOINT_PAUSE`` seconds;
    a commit itself never does (see the module's docstring). Another process's checkpointer
    may copy the same WAL: SQLite lets one at a time, and the other's attempt returns."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db, self._using = db, threading.Lock()
        self._poked, self._closing = threading.Event(), threading.Event()
        self._thread = threading.Thread(target=self._run, name="vantage-checkpoint", daemon=True)
        self._thread.start()

    def poke(self) -> None:
        self._poked.set()

    def copy(self) -> None:
        """Copy the WAL now, in the caller's thread."""
        with self._using, contextlib.suppress(sqlite3.Error):  # busy, or the disk away: a poke tries again
            self._db.execute("PRAGMA wal_checkpoint(PASSIVE)")

    def close(self) -> None:
        self._closing.set()
        self._poked.set()
        self._thread.join()
        self._db.close()

    def _run(self) -> None:
        while True:
            self._poked.wait()
            if self._closing.is_set():
                return
            self._poked.clear()
            self.copy()
            self._closing.wait(CHECKPOINT_PAUSE)


class _SQLiteWriting(Writing):
    def _executemany(self, text: str, rows: list[tuple]) -> None:
        self._db.executemany(text, rows)

    def _write_base_rows(self, rows: Iterator[tuple]) -> None:
        self._db.executemany(f"INSERT INTO bases ({COLUMNS}) VALUES ({', '.join('?' * 9)})", rows)


def _document(db: sqlite3.Connection, doc_id: str) -> dict[str, Any]:
    row = db.execute(META_QUERY + " WHERE id = ?", (doc_id,)).fetchone()
    if row is None:
        raise NotFound(f"document {doc_id!r} not found")
    return meta_of(row)


def _raise_if_full(error: object) -> None:
    if isinstance(error, sqlite3.OperationalError) and error.sqlite_errorcode == sqlite3.SQLITE_FULL:
        raise StorageFull(f"the store is full ({error}): nothing was written; free some space") from error
