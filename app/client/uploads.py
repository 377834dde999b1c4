"""What an import sends: a body streamed from its source (a path, bytes, a binary file, items
or lines; for the async client an async iterable too), gzip'd on the way if asked, and, past
the client's ``part_bytes``, the upload of parts it goes as instead (``POST .../uploads``, a
``PUT`` a part, the commit), which no body cap limits.

The clients' ``import_items`` and ``import_stream`` build their body here (:func:`_upload`,
:func:`_alines`, :func:`_zipped`) and send it with :func:`_send` / :func:`_asend`, through the
client's own ``_call``: nothing here holds a connection.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import zlib
from collections.abc import AsyncIterable, AsyncIterator, Awaitable, Callable, Iterable, Iterator
from pathlib import Path
from typing import IO, Any

import httpx

from app.client import VantageError, _nothing, _seg

__all__ = [
    "CHUNK",
    "NDJSON",
    "PART_BYTES",
    "PART_TRIES",
]

NDJSON = {"content-type": "application/x-ndjson"}
CHUNK = 1 << 20  # bytes an upload's chunk holds (before gzip)
PART_BYTES = 64 << 20  # an import bigger than this goes as an upload of parts this big
PART_TRIES = 3  # times a part is sent before its import gives up (sending one again is harmless)


# -- the body --------------------------------------------------------------------------------------


def _line(entry: Any) -> bytes:
    """An item (a dict), or a line (str or bytes), as one NDJSON line."""
    if isinstance(entry, dict):
        return json.dumps(entry, separators=(",", ":"), ensure_ascii=False).encode() + b"\n"
    if isinstance(entry, str):
        entry = entry.encode()
    if not isinstance(entry, (bytes, bytearray, memoryview)):
        raise TypeError(f"an import takes items (dicts) or lines (str or bytes), not {type(entry).__name__}")
    entry = bytes(entry)
    return entry if entry.endswith(b"\n") else entry + b"\n"


class _Gzip:
    """Chunks compressed as they pass (``Content-Encoding: gzip``)."""

    def __init__(self) -> None:
        self.z = zlib.compressobj(6, zlib.DEFLATED, 31)

    def __call__(self, chunk: bytes) -> bytes:
        return self.z.compress(chunk)

    def end(self) -> bytes:
        return self.z.flush()


def _batched(lines: Iterable[bytes]) -> Iterator[bytes]:
    """Lines joined into chunks of about ``CHUNK`` bytes."""
    batch: list[bytes] = []
    size = 0
    for line in lines:
        batch.append(line)
        size += len(line)
        if size >= CHUNK:
            yield b"".join(batch)
            batch, size = [], 0
    if batch:
        yield b"".join(batch)


def _zipped(chunks: Iterable[bytes]) -> Iterator[bytes]:
    gz = _Gzip()
    for chunk in chunks:
        if out := gz(chunk):
            yield out
    yield gz.end()


def _too_big_a_body(error: VantageError) -> bool:
    """Whether ``error`` refused one body for its size (gzip inflating past the cap): an upload
    of parts is not held to it."""
    return error.status == 413 and "VANTAGE_MAX_BODY_BYTES" in str(error.detail)


class _Parts:
    """Chunks regrouped into parts of ``size`` bytes: ``add`` a chunk, take the parts it
    filled; ``rest`` is the last, shorter one (b"" if none)."""

    def __init__(self, size: int) -> None:
        self.size, self._have = size, 0
        self._held: list[bytes] = []

    def add(self, chunk: bytes) -> list[bytes]:
        self._held.append(chunk)
        self._have += len(chunk)
        full = []
        while self._have >= self.size:
            joined = b"".join(self._held)
            full.append(joined[: self.size])
            self._held, self._have = [joined[self.size :]], self._have - self.size
        return full

    def rest(self) -> bytes:
        return b"".join(self._held)


def _parts(chunks: Iterable[bytes], size: int) -> Iterator[bytes]:
    """``chunks`` regrouped into parts of ``size`` bytes (the last one shorter)."""
    if isinstance(chunks, list) and len(chunks) == 1:  # one body in memory: sliced, each byte copied once
        body = chunks[0]
        yield from (body[start : start + size] for start in range(0, len(body), size))
        return
    parts = _Parts(size)
    for chunk in chunks:
        yield from parts.add(chunk)
    if rest := parts.rest():
        yield rest


async def _aparts(chunks: AsyncIterable[bytes], size: int) -> AsyncIterator[bytes]:
    """As :func:`_parts`, of an async iterable."""
    parts = _Parts(size)
    async for chunk in chunks:
        for part in parts.add(chunk):
            yield part
    if rest := parts.rest():
        yield rest


def _upload_options(headers: dict[str, str], replace: bool) -> dict[str, str]:
    """An upload's options for a body sent with ``headers``."""
    return {
        "format": "json" if headers["content-type"] == "application/json" else "ndjson",
        "encoding": headers.get("content-encoding", "identity"),
        "mode": "replace" if replace else "upsert",
    }


def _read_chunks(file: IO[bytes]) -> Iterator[bytes]:
    while chunk := file.read(CHUNK):
        yield chunk


def _kind_of_file(path: Path, gzipped: bool) -> str:
    """NDJSON or a JSON array, by the first character that is not blank."""
    import gzip

    with gzip.open(path, "rb") if gzipped else open(path, "rb") as f:
        head = f.read(4096).lstrip()
    return "application/json" if head.startswith(b"[") else NDJSON["content-type"]


def _gzipped_file(path: Path) -> bool:
    with open(path, "rb") as f:
        return f.read(2) == b"\x1f\x8b"


def _upload(source: Any, gzip: bool) -> tuple[Any, dict[str, str], str]:
    """``(content, headers, what)`` for an import of ``source`` (sync).

    A path (str or ``os.PathLike``) is streamed from disk, a gzip file as it is; bytes go as
    they are; a binary file object is read in chunks; any other iterable holds items (dicts)
    or lines (str or bytes). With ``gzip`` the body is compressed on the way.
    """
    headers = dict(NDJSON)
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        zipped = _gzipped_file(path)
        headers["content-type"] = _kind_of_file(path, zipped)

        def chunks() -> Iterator[bytes]:
            with open(path, "rb") as f:
                yield from _read_chunks(f)

        if zipped:
            return chunks(), {**headers, "content-encoding": "gzip"}, str(path)
        body: Iterable[bytes] = chunks()
    elif isinstance(source, (bytes, bytearray, memoryview)):
        source = bytes(source)
        if source.lstrip()[:1] == b"[":
            headers["content-type"] = "application/json"
        if not gzip:
            return source, headers, "bytes"
        body = [source]
    elif hasattr(source, "read"):
        body = _read_chunks(source)
    elif isinstance(source, dict):
        raise TypeError("an import takes many items: pass [item] (or use put_item for one)")
    elif isinstance(source, Iterable):
        body = _batched(_line(entry) for entry in source)
    else:
        raise TypeError(f"cannot import from {type(source).__name__}")
    if gzip:
        return _zipped(body), {**headers, "content-encoding": "gzip"}, "stream"
    return body, headers, "stream"


async def _aiter(chunks: Iterable[bytes]) -> AsyncIterator[bytes]:
    """A sync iterator read in a thread a chunk at a time (a file on disk blocks)."""
    it = iter(chunks)
    while (chunk := await asyncio.to_thread(next, it, None)) is not None:  # chunks are bytes
        yield chunk


async def _alines(source: AsyncIterable[Any], gzip: bool) -> AsyncIterator[bytes]:
    gz = _Gzip() if gzip else None
    batch: list[bytes] = []
    size = 0
    async for entry in source:
        line = _line(entry)
        batch.append(line)
        size += len(line)
        if size >= CHUNK:
            chunk = b"".join(batch)
            batch, size = [], 0
            if gz is None:
                yield chunk
            elif out := gz(chunk):
                yield out
    chunk = b"".join(batch)
    if gz is None:
        if chunk:
            yield chunk
    else:
        yield gz(chunk) + gz.end()


# -- the sending: one body, or an upload of parts ----------------------------------------------------


def _send(
    call: Callable[..., Any],
    doc: str,
    content: bytes | Iterable[bytes],
    headers: dict[str, str],
    replace: bool,
    part_bytes: int,
) -> dict:
    """Import ``content`` through ``call`` (a client's ``_call``): in one body, or, past
    ``part_bytes``, as an upload (``POST .../uploads``, each part ``PUT`` as it fills, tried up
    to PART_TRIES times, then the commit), which no body cap limits; one part is held in memory
    at a time."""
    path = f"/documents/{_seg(doc)}"
    parts = _parts([content] if isinstance(content, bytes) else content, part_bytes)
    first, second = next(parts, b""), next(parts, None)
    if second is None:
        params = {"mode": "replace"} if replace else None
        try:
            return call("POST", f"{path}/items", content=first, headers=headers, params=params)
        except VantageError as error:
            if not _too_big_a_body(error):
                raise
        # a gzip body that inflates past one body's cap: an upload takes it
    upload = call("POST", f"{path}/uploads", json=_upload_options(headers, replace))["id"]
    try:
        count = 0
        for count, part in enumerate(itertools.chain([first], [second] if second else [], parts), 1):
            for attempt in range(PART_TRIES):
                try:
                    call("PUT", f"{path}/uploads/{upload}/parts/{count}", content=part)
                    break
                except httpx.TransportError:
                    if attempt == PART_TRIES - 1:
                        raise
        return call("POST", f"{path}/uploads/{upload}/commit", json={"parts": count})
    except BaseException:
        with contextlib.suppress(Exception):  # nothing was imported: leave nothing behind
            call("DELETE", f"{path}/uploads/{upload}", _nothing)
        raise


async def _asend(
    call: Callable[..., Awaitable[Any]],
    doc: str,
    content: bytes | AsyncIterable[bytes],
    headers: dict[str, str],
    replace: bool,
    part_bytes: int,
) -> dict:
    """As :func:`_send`, through an async client's ``_call``."""
    path = f"/documents/{_seg(doc)}"
    parts = _aparts(_aiter([content]) if isinstance(content, bytes) else content, part_bytes)
    first, second = await anext(parts, b""), await anext(parts, None)
    if second is None:
        params = {"mode": "replace"} if replace else None
        try:
            return await call("POST", f"{path}/items", content=first, headers=headers, params=params)
        except VantageError as error:
            if not _too_big_a_body(error):
                raise
        # a gzip body that inflates past one body's cap: an upload takes it
    upload = (await call("POST", f"{path}/uploads", json=_upload_options(headers, replace)))["id"]

    async def every() -> AsyncIterator[bytes]:
        yield first
        if second is not None:
            yield second
        async for part in parts:
            yield part

    try:
        count = 0
        async for part in every():
            count += 1
            for attempt in range(PART_TRIES):
                try:
                    await call("PUT", f"{path}/uploads/{upload}/parts/{count}", content=part)
                    break
                except httpx.TransportError:
                    if attempt == PART_TRIES - 1:
                        raise
        return await call("POST", f"{path}/uploads/{upload}/commit", json={"parts": count})
    except BaseException:
        with contextlib.suppress(Exception):  # nothing was imported: leave nothing behind
            await call("DELETE", f"{path}/uploads/{upload}", _nothing)
        raise
