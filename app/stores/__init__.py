"""Where documents are kept: one interface (``Store``), two engines. SQLite, embedded under the
data directory, is the default; PostgreSQL (``VANTAGE_DATABASE_URL``) lets replicas on several
machines share one store."""

from pathlib import Path
from urllib.parse import urlsplit

from .base import Change, Store, StoreError, StoreUnavailable, Writing
from .sqlite import SQLiteStore

__all__ = [
    "Change",
    "SQLiteStore",
    "Store",
    "StoreError",
    "StoreUnavailable",
    "Writing",
    "open_store",
    "where",
]


def open_store(data_dir: Path, database_url: str | None = None) -> Store:
    """The store at ``database_url`` (PostgreSQL) if given, else the SQLite one in ``data_dir``.

    :raises StoreError: if it cannot be used (unreachable, or of another format); the message says why
    """
    if database_url:
        if not database_url.startswith(("postgresql://", "postgres://")):
            raise StoreError(
                f"VANTAGE_DATABASE_URL must be a postgresql:// URL, not {database_url.split(':')[0]!r}"
            )
        from .postgres import PostgresStore  # psycopg loads only when it is used

        return PostgresStore(database_url)
    return SQLiteStore(data_dir)


def where(data_dir: Path, database_url: str | None = None) -> str:
    """Where ``open_store`` keeps documents, for people: no password.

    >>> where(Path("data"), "postgresql://ann:s3cret@db.example:5433/vantage")
    'PostgreSQL at db.example:5433/vantage (user ann)'
    >>> where(Path("data"))
    'SQLite at data/vantage.sqlite3'
    """
    if database_url:
        url = urlsplit(database_url)
        port = f":{url.port}" if url.port else ""
        user = f" (user {url.username})" if url.username else ""
        return f"PostgreSQL at {url.hostname or 'localhost'}{port}{url.path}{user}"
    return f"SQLite at {data_dir / 'vantage.sqlite3'}"
