"""Settings, read from the environment with the prefix ``VANTAGE_``."""

import ipaddress
import os
from functools import lru_cache
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["LOOPBACK_NAMES", "Settings", "get_settings", "is_loopback"]

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1")


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="VANTAGE_")

    data_dir: Path = Field(
        Path("./data"), description="where the SQLite store lives, and each process's snapshot files"
    )
    database_url: str | None = Field(
        None,
        description="a postgresql:// URL: keep documents in that PostgreSQL database, shared by "
        "replicas on several machines, instead of SQLite under the data directory",
    )
    catch_up_ms: int = Field(
        1000,
        ge=0,
        description="how long a request with a `min_version` this server has not reached waits "
        "for it (then 503 with Retry-After)",
    )
    host: str = Field("127.0.0.1", description="address to bind")
    port: int = 8000
    max_body_bytes: int = Field(
        256 << 20, description="largest import body (413 beyond); an import peaks at ~1.7x it"
    )
    max_upload_bytes: int = Field(
        2 << 30,
        description="most bytes an upload's parts hold together, and its body once inflated (413 "
        "beyond); each part is one body of at most VANTAGE_MAX_BODY_BYTES. Its commit holds the "
        "items' boxes in memory (their JSON, ids and index go to files), ~1.7x its body at the "
        "peak for small items: size it to the machine",
    )
    max_json_bytes: int = Field(64 << 10, description="largest body of any other request (413 beyond)")
    body_timeout: float = Field(
        300.0, gt=0, description="seconds to receive a whole request body (408 beyond)"
    )
    max_line_bytes: int = Field(64 << 10, description="longest NDJSON line (422 beyond)")
    max_data_bytes: int = Field(4 << 10, description="largest `data` object of one item, as JSON")
    max_imports: int = Field(1, ge=1, description="imports decoded at once; others wait their turn")
    default_limit: int = Field(10_000, description="items per response when the client sets no limit")
    max_limit: int = Field(100_000, description="items (and left ids) per response, whatever the client asks")
    lod_budget: int = Field(
        5000,
        ge=1,
        description="entries (items and aggregates) per full-HD screen an answer at a level of "
        "detail may hold; past it, a coarser band answers",
    )
    cache_mb: int | None = Field(
        None,
        ge=1,
        description="megabytes open documents may hold per worker; past it the least recently used "
        "close, all but the last used (default: a quarter of the machine's memory, shared among the "
        "workers)",
    )
    save_edits_seconds: float = Field(
        30.0,
        gt=0,
        description="an open document's edits are saved beside its base this long after the first "
        "not saved yet (or 20 times as long as the last save took, if longer), and at every 2,048: "
        "a start after a crash replays from the store only those made since",
    )
    tile_cache_mb: int = Field(
        128,
        ge=1,
        description="megabytes of zoomed-out tiles each open document keeps per worker, counted in "
        "VANTAGE_CACHE_MB (at most a quarter of it); the least recently used are dropped past it",
    )
    frames_mb: int = Field(
        32,
        ge=0,
        description="megabytes of decoded item JSON each worker keeps: a snapshot file holds it "
        "compressed in frames of ~16 KiB, which an answer decodes (0: every time)",
    )
    gzip_min_bytes: int | None = Field(
        1024,
        ge=0,
        description="answers of at least this many bytes are gzip-compressed for clients that "
        "accept it (none: never, as behind a proxy that compresses); the stream uses permessage-deflate",
    )
    telemetry: bool = Field(
        False,
        description="OpenTelemetry spans, metrics and logs of each request (FastAPI's), through the "
        "providers OpenTelemetry is configured with; off, no request pays for looking them up",
    )
    workers: int = Field(1, ge=1, description="processes serving on one port (`vantage serve --workers`)")
    max_items: int = Field(10_000_000, description="items one document may hold (413 beyond)")
    import_memory_mb: int = Field(
        1400,
        ge=256,
        description="megabytes an import's build aims to hold at its peak (a compaction's too: its "
        "fold of the edits and its build): its runs are sized to what the runtime (~250 MB) and what it "
        "holds whole (~7 bytes an item) leave of it, 16-256 MB; a document needing more still "
        "imports, with a warning",
    )
    max_documents: int = Field(10_000, description="documents the store may hold (409 beyond)")
    max_streams: int = Field(1000, ge=1, description="open streams at once (close code 1013 beyond)")
    max_stream_rate: float = Field(120.0, description="viewports a stream client may send per second")
    stream_unread_mb: int = Field(
        256,
        ge=1,
        description="megabytes of stream answers not yet taken by their clients that a worker "
        "holds, all streams together; past it an answer waits for room (then the stream closes, 1013)",
    )
    stream_send_timeout: float = Field(
        10.0,
        gt=0,
        description="seconds an answer may wait for a client "
        "that does not read (then the stream is closed, code 1008)",
    )
    search_threads: int = Field(
        1, ge=1, description="searches run at once per worker, in a pool of their own"
    )
    search_queue: int = Field(64, ge=0, description="searches that may wait for one of those (503 beyond)")
    tokens: str = Field("", description="comma-separated bearer tokens that may write; none: loopback only")
    tokens_file: Path | None = Field(None, description="a file of tokens, one a line, added to `tokens`")
    read_token: bool = Field(
        False, description="reads need a token too: documents, and `/stats` and the API docs"
    )
    jwt_secret: str = Field(
        "",
        description="comma-separated secrets (32 bytes or more each) that verify signed access "
        "tokens (JWT, HS256); during a rotation list the new one first, then the old",
    )
    jwt_public_key: Path | None = Field(
        None,
        description="a PEM public key (Ed25519, P-256 or RSA) that verifies signed access tokens instead",
    )
    jwt_audience: str = Field("", description="when set, a signed token's `aud` must name it")
    cors_origins: str = Field("", description="comma-separated origins allowed by CORS (none by default)")
    allowed_hosts: str = Field(
        "",
        description="comma-separated names the Host header may carry; default: "
        "the loopback names when bound to loopback, else any",
    )

    @property
    def import_bytes(self) -> int:
        """What an import's build (and a compaction's) aims to hold at its peak, in bytes: the
        ``SnapshotFiles`` they build into size each build's ``MemoryBudget`` to it."""
        return self.import_memory_mb << 20

    @property
    def cache_bytes(self) -> int:
        """The memory budget of each worker's open documents, in bytes."""
        if self.cache_mb is not None:
            return self.cache_mb << 20
        return max(64 << 20, os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 4 // self.workers)

    def cap(self, limit: int | None) -> int:
        """Items an answer may hold: the client's ``limit`` (or the default), within the server's."""
        return min(limit or self.default_limit, self.max_limit)

    @property
    def jwt_configured(self) -> bool:
        """Whether signed access tokens are accepted (a key to verify them is set)."""
        return bool(_split(self.jwt_secret)) or self.jwt_public_key is not None

    @property
    def tokens_required(self) -> bool:
        """Whether writes need a token: decided by the settings, never by a file's content."""
        return bool(_split(self.tokens)) or self.tokens_file is not None or self.jwt_configured

    @property
    def origins(self) -> list[str]:
        return _split(self.cors_origins)

    @property
    def hosts(self) -> list[str] | None:
        """Host names requests may name; None: any."""
        if names := _split(self.allowed_hosts):
            return None if "*" in names else [n.lower() for n in names]
        return list(LOOPBACK_NAMES) if is_loopback(self.host) else None


def is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return host == "localhost"


def _split(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


@lru_cache
def get_settings() -> Settings:
    """The process's settings; tests override this dependency."""
    return Settings()
