"""An import's body, however it came (one request's, or an upload's parts end to end): its
NDJSON lines measured as it arrives, inflated as it is read when gzipped, then decoded, packed
and written all or nothing. The import route and an upload's commit both import through
:func:`import_body`."""

import asyncio
import gzip
import io
import logging
import zlib
from collections.abc import Callable
from functools import partial
from typing import IO

from fastapi.concurrency import run_in_threadpool

from .config import Settings
from .documents import Document, pack
from .errors import Invalid, TooMany
from .items import Readable, decode_json_array, decode_ndjson, line_too_long

__all__ = ["INFLATE_CHUNK", "Inflated", "Lines", "import_body"]

log = logging.getLogger("vantage.import")
INFLATE_CHUNK = 1 << 20  # bytes a whole read of a gzip body inflates at a time


async def import_body(
    doc: Document,
    settings: Settings,
    turns: asyncio.Semaphore,
    body: IO[bytes],
    ndjson: bool,
    gzipped: bool,
    mode: str,
    inflate: tuple[int, str],
) -> dict:
    """Import ``body`` (NDJSON, else a JSON array; gzipped or not, inflated up to ``inflate``:
    the bytes, and the setting that says so) into ``doc`` all or nothing: the import route's
    work, and an upload's commit's. Decoded items cost a few times their bytes: imports take
    ``turns`` (the app's, VANTAGE_MAX_IMPORTS at a time).

    :raises ServiceError: a bad line or item (422, naming it), too many items or bytes (413),
        a full disk (507)
    """
    async with turns:
        log.info("import into %s: decoding its body", doc.id)
        text: Readable = Inflated(body, *inflate) if gzipped else body
        batches = (
            decode_ndjson(text, settings.max_line_bytes, settings.max_data_bytes)
            if ndjson
            else decode_json_array(text, settings.max_data_bytes)
        )
        table = await run_in_threadpool(pack, batches, doc.files.directory)
        count, version = await doc.write_import(table, settings.max_items, mode == "replace")
        del table
        log.info("import into %s: committed version %d", doc.id, version)
    return {"imported": count, "version": version}


class Lines:
    """An NDJSON body's lines counted as it arrives: a line is refused once more than
    ``max_line_bytes`` of it came (as ``decode_ndjson`` refuses it, with the same words), not
    after the whole body is spooled. A line that arrives whole inside one chunk is left to
    the decoding (a chunk is a few kB to 64 kB)."""

    def __init__(self, max_line_bytes: int) -> None:
        self.max_line_bytes = max_line_bytes
        self.number, self.begun = 1, 0  # the line arriving, and its bytes so far

    def arrived(self, chunk: bytes) -> None:
        """:raises ItemError: for a line past ``max_line_bytes``, naming it and the setting"""
        if (newlines := chunk.count(b"\n")) > 0:
            self.number += newlines
            self.begun = len(chunk) - chunk.rfind(b"\n") - 1
        else:
            self.begun += len(chunk)
        if self.begun > self.max_line_bytes:
            raise line_too_long(self.number, self.max_line_bytes)


class Inflated(io.RawIOBase):
    """A gzip body, decompressed as it is read, at most ``limit`` bytes of it (a small body can
    inflate a thousandfold).

    :raises TooMany: past ``limit`` decompressed bytes
    :raises Invalid: if the body is not gzip
    """

    def __init__(self, raw: IO[bytes], limit: int, setting: str = "VANTAGE_MAX_BODY_BYTES") -> None:
        self._gzip, self._limit, self._read = gzip.GzipFile(fileobj=raw, mode="rb"), limit, 0
        self._setting = setting

    def readable(self) -> bool:
        return True

    def readline(self, size: int | None = -1) -> bytes:
        return self._count(lambda: self._gzip.readline(size))

    def read(self, size: int | None = -1) -> bytes:
        if size is None or size < 0:  # all of it: a piece at a time, so the cap is met as it is reached
            return b"".join(iter(partial(self.read, INFLATE_CHUNK), b""))
        return self._count(lambda: self._gzip.read(size))

    def _count(self, read: Callable[[], bytes]) -> bytes:
        try:
            data = read()
        except (OSError, EOFError, zlib.error) as error:
            raise Invalid(f"the body says `Content-Encoding: gzip` but is not gzip: {error}") from None
        self._read += len(data)
        if self._read > self._limit:
            raise TooMany(
                f"the body inflates past {self._limit} bytes, the most an import takes ({self._setting})"
            )
        return data
