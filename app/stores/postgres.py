"""The shared store: PostgreSQL, for replicas on several machines (``VANTAGE_DATABASE_URL``).

Same layout as the embedded store. A write locks its document's row (``SELECT ... FOR
UPDATE``), so writers on any replica take turns per document and versions stay gap-free; a
base is streamed in with ``COPY`` (binary), a chunk at a time. The change log's ``seq`` is
commit-ordered because a write takes a transaction-scoped advisory lock just before it
appends its row, and holds it through the commit: no row with a smaller ``seq`` can commit
after one with a larger.

Replicas learn of each other's writes from ``NOTIFY``, sent by every write on commit, but only
as a wake-up: the log is the truth, read from the last ``seq`` seen, and ``changed()`` also says
yes every ``POLL_SECONDS``, so a missed notification delays, never loses. While the server
cannot be reached, every call raises ``StoreUnavailable``: at once from when the listener
thread notices (a refused connection at once, a silent host within ~15 s of keepalives), so no
request waits out a connect timeout; the listener reconnects by itself, then says ``changed()``.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from typing import Any, TypedDict

import psycopg
import psycopg_pool

from ..errors import Conflict, NotFound, StorageFull
from .base import (
    META_QUERY,
    Store,
    StoreError,
    StoreUnavailable,
    Writing,
    meta_of,
)

__all__ = ["PostgresStore"]

log = logging.getLogger("vantage.store")

FORMAT = 3  # 2: base rows carry their codec; 3: and their rowset (stores/base.py)
MIGRATIONS = {  # to the next format
    1: "ALTER TABLE bases ADD COLUMN codec smallint NOT NULL DEFAULT 0",
    2: """
    ALTER TABLE documents ADD COLUMN rowset bigint NOT NULL DEFAULT 0;
    ALTER TABLE bases ADD COLUMN rowset bigint NOT NULL DEFAULT 0;
    ALTER TABLE bases DROP CONSTRAINT bases_pkey, ADD PRIMARY KEY (doc_id, rowset, chunk)
    """,
}
SCHEMA = """
CREATE TABLE IF NOT EXISTS vantage_format (format integer NOT NULL);
CREATE TABLE IF NOT EXISTS documents (
    id text PRIMARY KEY,
    name text NOT NULL,
    created double precision NOT NULL,
    version bigint NOT NULL DEFAULT 0,
    base_id text,
    base_version bigint NOT NULL DEFAULT 0,
    items bigint NOT NULL DEFAULT 0,
    bounds text,
    rowset bigint NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS bases (
    doc_id text NOT NULL REFERENCES documents(id) ON DELETE CASCADE,
    rowset bigint NOT NULL DEFAULT 0,
    chunk integer NOT NULL,
    ids bytea NOT NULL, id_offsets bytea NOT NULL,
    bodies bytea NOT NULL, body_offsets bytea NOT NULL,
    boxes bytea NOT NULL,
    codec smallint NOT NULL DEFAULT 0,
    PRIMARY KEY (doc_id, rowset, chunk)
);
-- Compressed already (zstd, stores/base.py): PostgreSQL's own compression would only cost time
ALTER TABLE bases ALTER COLUMN ids SET STORAGE EXTERNAL, ALTER COLUMN bodies SET STORAGE EXTERNAL,
    ALTER COLUMN boxes SET STORAGE EXTERNAL, ALTER COLUMN id_offsets SET STORAGE EXTERNAL,
    ALTER COLUMN body_offsets SET STORAGE EXTERNAL;
CREATE TABLE IF NOT EXISTS edits (
    doc_id text NOT NULL REFERENCES documents(id) ON DELETE CASCADE,
    item_id text NOT NULL,
    version bigint NOT NULL,
    x0 double precision, y0 double precision, x1 double precision, y1 double precision,
    body bytea,
    PRIMARY KEY (doc_id, item_id)
);
CREATE TABLE IF NOT EXISTS changes (
    seq bigint GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    doc_id text NOT NULL,
    version bigint NOT NULL,
    kind text NOT NULL
);
CREATE INDEX IF NOT EXISTS changes_of_document ON changes (doc_id, version);
"""
CHANNEL = "vantage_changes"
# Advisory lock keys: laying the tables out, appending to the log, creating a document
SCHEMA_LOCK, LOG_LOCK, CREATE_LOCK = 0x56414E54, 0x56414E55, 0x56414E56
POLL_SECONDS = 1.0  # changed() says yes at least this often, whatever the notifications


class _Connect(TypedDict):
    """libpq connection parameters, as keyword arguments of ``psycopg.connect``."""

    connect_timeout: int
    keepalives: int
    keepalives_idle: int
    keepalives_interval: int
    keepalives_count: int


# A server that stops answering (a host gone, not a refused connection) is noticed in seconds
CONNECT: _Connect = {
    "connect_timeout": 5,
    "keepalives": 1,
    "keepalives_idle": 5,
    "keepalives_interval": 2,
    "keepalives_count": 3,
}
RECONNECT_SECONDS = 0.5


class PostgresStore(Store):
    engine = "postgresql"

    def __init__(self, url: str, pool_size: int = 16) -> None:
        super().__init__()
        # Writes lock their document's row, not the store: writers of different documents
        # need not take turns (a document's own writers still queue, on Document.write)
        self.turn = _NoTurn()
        self.url = url
        try:
            with psycopg.connect(url, autocommit=True, **CONNECT) as db, db.transaction():
                db.execute("SELECT pg_advisory_xact_lock(%s)", (SCHEMA_LOCK,))  # one replica lays it out
                laid_out = _value(db.execute("SELECT to_regclass('vantage_format') IS NOT NULL"))
                found = db.execute("SELECT format FROM vantage_format").fetchone() if laid_out else None
                if found is None:  # only then: its ALTER TABLE would wait for every write under way
                    db.execute(SCHEMA)
                    db.execute("INSERT INTO vantage_format VALUES (%s)", (FORMAT,))
                elif found[0] in MIGRATIONS:  # an earlier layout: brought up to this one
                    for step in range(found[0], FORMAT):
                        db.execute(MIGRATIONS[step])
                    db.execute("UPDATE vantage_format SET format = %s", (FORMAT,))
                elif found[0] != FORMAT:
                    raise StoreError(
                        f"the database holds a store of format {found[0]}, which this version (format "
                        f"{FORMAT}) cannot read: point VANTAGE_DATABASE_URL at another database"
                    )
        except psycopg.OperationalError as error:
            raise StoreError(
                f"cannot reach PostgreSQL at VANTAGE_DATABASE_URL ({_first_line(error)})"
            ) from None
        self._pool = psycopg_pool.ConnectionPool(
            url,
            min_size=2,
            max_size=pool_size,
            kwargs={"autocommit": True, **CONNECT},
            check=psycopg_pool.ConnectionPool.check_connection,  # a restarted server leaves dead ones
            timeout=5.0,
            open=True,
        )
        self._reachable = True
        self._woken = threading.Event()
        self._polled = time.monotonic()
        self._closing = threading.Event()
        self._listener = threading.Thread(target=self._listen, name="vantage-listen", daemon=True)
        self._listener.start()

    def close(self) -> None:
        self._closing.set()
        self._listener.join(timeout=5)
        self._pool.close()

    # -- following ---------------------------------------------------------------------------

    def _listen(self) -> None:
        """Wake ``changed()`` on each notification; keep reconnecting while the server is away."""
        while not self._closing.is_set():
            try:
                with psycopg.connect(self.url, autocommit=True, **CONNECT) as db:
                    db.execute(f"LISTEN {CHANNEL}")
                    if not self._reachable:
                        log.warning("PostgreSQL is back: catching up from the change log")
                    self._reachable = True
                    self._wake()  # whatever committed while away is in the log
                    while not self._closing.is_set():
                        for _ in db.notifies(timeout=0.25, stop_after=1):
                            self._wake()
            except psycopg.Error as error:
                if self._reachable:
                    log.warning("PostgreSQL cannot be reached (%s): serving what is held", _first_line(error))
                self._reachable = False
                self._closing.wait(RECONNECT_SECONDS)

    def _wake(self) -> None:
        self._woken.set()
        with suppress(RuntimeError):  # an event loop that closed before the store did
            self.on_change()

    def changed(self) -> bool:
        """Cost: an event and a clock read. Never while the server is away: nothing to learn."""
        if not self._reachable:
            return False
        now = time.monotonic()
        if self._woken.is_set() or now - self._polled >= POLL_SECONDS:
            self._woken.clear()
            self._polled = now
            return True
        return False

    def status(self) -> dict[str, Any]:
        """As the listener last found the server: no query, so a hung server cannot hang a probe."""
        if not self._reachable:
            return {"store": self.engine, "reachable": False, "detail": "PostgreSQL cannot be reached"}
        return {"store": self.engine, "reachable": True}

    # -- documents ---------------------------------------------------------------------------

    def create_document(self, name: str, max_documents: int | None = None) -> dict[str, Any]:
        doc_id = uuid.uuid4().hex[:12]
        doc = {"id": doc_id, "name": name, "created": time.time()}
        with self._write() as db:
            # Creators count one at a time; a table lock would also wait for every write under way
            db.execute("SELECT pg_advisory_xact_lock(%s)", (CREATE_LOCK,))
            held = _value(db.execute("SELECT count(*) FROM documents"))
            if max_documents is not None and held >= max_documents:
                raise Conflict(
                    f"the store holds {held} documents, the most it may (VANTAGE_MAX_DOCUMENTS): delete one first"
                )
            db.execute(
                "INSERT INTO documents (id, name, created) VALUES (%(id)s, %(name)s, %(created)s)", doc
            )
        return self.document(doc_id)

    def document(self, doc_id: str) -> dict[str, Any]:
        with self._read() as db:
            return _document(db, doc_id)

    @contextmanager
    def writing(self, doc_id: str) -> Iterator[Writing]:
        with self._write() as db:
            yield _PostgresWriting(db, _document(db, doc_id, lock=True))

    @contextmanager
    def _unlocked(self, doc_id: str) -> Iterator[Writing]:
        with self._write() as db:
            yield _PostgresWriting(db, {"id": doc_id})

    # -- connections -------------------------------------------------------------------------

    def _rows(self, text: str, *args: object) -> list[tuple]:
        with self._read() as db:  # binary: bytea arrives as bytes, not as hex text to decode
            return db.execute(text.replace("?", "%s"), args, binary=True).fetchall()

    @contextmanager
    def _read(self) -> Iterator[psycopg.Connection]:
        with self._unless_unreachable(), self._pool.connection() as db:
            yield db

    @contextmanager
    def _write(self) -> Iterator[psycopg.Connection]:
        """A transaction: committed when the block ends, rolled back if it raises (or if the
        server goes away: then nothing was written)."""
        with self._unless_unreachable(), self._pool.connection() as db, db.transaction():
            yield db

    @contextmanager
    def _unless_unreachable(self) -> Iterator[None]:
        if not self._reachable:
            raise StoreUnavailable(
                "the store (PostgreSQL) cannot be reached: nothing was written; try again soon"
            )
        try:
            yield
        except psycopg.errors.DiskFull as error:
            raise StorageFull(
                f"the store is full ({_first_line(error)}): nothing was written; free some space"
            ) from None
        except psycopg_pool.PoolTimeout as error:
            raise StoreUnavailable(
                f"the store (PostgreSQL) is busy ({_first_line(error)}): nothing was written; try again soon"
            ) from None
        except psycopg.OperationalError as error:
            if not _lost(error):
                raise  # a deadlock, a limit: a fault to fix, not to wait out
            raise StoreUnavailable(
                f"the store (PostgreSQL) cannot be reached ({_first_line(error)}): nothing was written; try again soon"
            ) from None


class _PostgresWriting(Writing):
    PARAM = "%s"

    def _executemany(self, text: str, rows: list[tuple]) -> None:
        with self._db.cursor() as cursor:
            cursor.executemany(text, rows)

    def _write_base_rows(self, rows: Iterator[tuple]) -> None:
        columns = "doc_id, rowset, chunk, ids, id_offsets, bodies, body_offsets, boxes, codec"
        with self._db.cursor().copy(f"COPY bases ({columns}) FROM STDIN (FORMAT BINARY)") as copy:
            copy.set_types(["text", "int8", "int4", "bytea", "bytea", "bytea", "bytea", "bytea", "int2"])
            for row in rows:  # streamed: one chunk's bytes at a time
                copy.write_row(row)

    def _log(self, version: int, kind: str) -> None:
        """Under the log's lock, held to the commit: rows commit in ``seq`` order. The
        notification goes out with the commit."""
        self._db.execute("SELECT pg_advisory_xact_lock(%s)", (LOG_LOCK,))
        super()._log(version, kind)
        self._db.execute("SELECT pg_notify(%s, %s)", (CHANNEL, self._id))


def _value(cursor: psycopg.Cursor[Any]) -> Any:
    """The one value of a query that always answers one row (an aggregate, say)."""
    row = cursor.fetchone()
    assert row is not None, "a query of one row answered none"
    return row[0]


def _document(db: psycopg.Connection, doc_id: str, lock: bool = False) -> dict[str, Any]:
    if "\x00" in doc_id:  # text cannot hold one: no such document, rather than the server's error
        raise NotFound(f"document {doc_id!r} not found")
    row = db.execute(META_QUERY + " WHERE id = %s" + (" FOR UPDATE" if lock else ""), (doc_id,)).fetchone()
    if row is None:
        raise NotFound(f"document {doc_id!r} not found")
    return meta_of(row)


class _NoTurn:
    """``async with store.turn:`` that waits for nothing."""

    async def __aenter__(self) -> None:
        return None

    async def __aexit__(self, *exc: object) -> None:
        return None


def _lost(error: psycopg.OperationalError) -> bool:
    """Whether ``error`` is the server gone or going: no connection (no SQLSTATE), a connection
    exception (class 08) or an operator's intervention (class 57P: a shutdown, a restart)."""
    state = error.sqlstate
    return state is None or state.startswith(("08", "57P"))


def _first_line(error: BaseException) -> str:
    return str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
