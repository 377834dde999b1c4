"""A Python client of a Vantage server (httpx, sync and async) and its pan stream.

One method a route, the same on :class:`Client` and :class:`AsyncClient` (whose methods are
awaited); a non-2xx answer raises :class:`VantageError`, carrying the status and the server's
``detail``::

    with Client("http://127.0.0.1:8000", token="s3cret") as vantage:
        doc = vantage.create_document("report")["id"]
        vantage.import_items(doc, Path("report.ndjson.gz"))  # streamed from disk
        vantage.import_items(doc, ({"id": f"n{i}", "x0": i, "y0": 0, "x1": i + 1, "y1": 1} for i in range(10)))
        vantage.viewport(doc, (0, 0, 1920, 1080), scale=0.5, min_px=1)
        with vantage.stream(doc, scale=0.5, min_px=1) as stream:
            stream.view((0, 0, 1920, 1080))  # what entered and left; stream.items holds the view
            stream.view((0, 500, 1920, 1580))

The simulator, the benchmarks and the tests talk to servers through this module (and start them
with :mod:`app.launch`) rather than each on its own. Its stream needs websockets, which uvicorn's
``standard`` extra installs.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import itertools
import json
import os
import time
import zlib
from collections.abc import AsyncIterable, AsyncIterator, Callable, Generator, Iterable, Iterator
from pathlib import Path
from typing import IO, Any
from urllib.parse import quote, urlencode

import httpx

__all__ = [
    "AsyncClient",
    "AsyncStream",
    "Client",
    "Stream",
    "VantageError",
]

NDJSON = {"content-type": "application/x-ndjson"}
CHUNK = 1 << 20  # bytes an upload's chunk holds (before gzip)
PART_BYTES = 64 << 20  # an import bigger than this goes as an upload of parts this big
PART_TRIES = 3  # times a part is sent before its import gives up (sending one again is harmless)
Rect = tuple[float, float, float, float]


# -- errors ----------------------------------------------------------------------------------------


class VantageError(httpx.HTTPStatusError):
    """The server refused: ``status`` (the HTTP code) and ``detail`` (its reason: a string, or
    FastAPI's list of validation errors). A refused or closed stream raises it too, with the
    status its close code stands for (4404 -> 404, 4401 -> 401, 4403 -> 403, 1013 -> 503, a
    bad viewport 422). An ``httpx.HTTPStatusError``, so code catching that goes on working."""

    def __init__(self, status: int, detail: Any, response: httpx.Response) -> None:
        self.status, self.detail = status, detail
        super().__init__(f"{status} {detail}", request=response.request, response=response)

    @classmethod
    def of(cls, response: httpx.Response) -> VantageError:
        try:
            detail = response.json().get("detail", response.text)
        except Exception:
            detail = response.text[:500] or response.reason_phrase
        return cls(response.status_code, detail, response)

    @classmethod
    def made(cls, status: int, detail: str, url: str) -> VantageError:
        """An error with no HTTP answer behind it (the stream's)."""
        response = httpx.Response(status, json={"detail": detail}, request=httpx.Request("GET", url))
        return cls(status, detail, response)


def _checked(response: httpx.Response) -> httpx.Response:
    if response.is_error:
        if not response.is_closed:
            response.read()
        raise VantageError.of(response)
    return response


async def _checked_async(response: httpx.Response) -> httpx.Response:
    if response.is_error:
        if not response.is_closed:
            await response.aread()
        raise VantageError.of(response)
    return response


# -- what a request is, for both clients -------------------------------------------------------


def _seg(value: str) -> str:
    """``value`` as one path segment: every reserved character escaped (an item id may hold ``/``)."""
    return quote(value, safe="").replace(".", "%2E")


def _rect(rect: Iterable[float]) -> str:
    return ",".join(repr(float(v)) for v in rect)


def _params(**params: Any) -> dict[str, Any]:
    return {k: v for k, v in params.items() if v is not None}


def _json(response: httpx.Response) -> Any:
    return response.json()


def _page(response: httpx.Response) -> list:
    """A page of a list, and the pages after it (followed through the ``Link`` header)."""
    page = response.json()
    next_page = response.links.get("next", {}).get("url")
    if next_page is None:
        return page
    return _Next(page, next_page)


class _Next(list):
    """A page whose next one is still to fetch (at ``url``): the client's ``_call`` follows it."""

    def __init__(self, page: list, url: str) -> None:
        super().__init__(page)
        self.url = url


def _nothing(response: httpx.Response) -> None:
    return None


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


Token = str | Callable[[], str] | None  # a token, or a function that returns a fresh one
RENEW_SECONDS = 60.0  # a token from a function is renewed this long before it expires


class _Bearer(httpx.Auth):
    """``Authorization: Bearer`` with a token, or with what a function returns, called again
    when the last one is within RENEW_SECONDS of its ``exp`` (read from the JWT, unverified:
    the server verifies)."""

    def __init__(self, token: Token) -> None:
        self.source, self.token = token, None if callable(token) else token

    def current(self) -> str | None:
        if callable(self.source) and (self.token is None or _expiring(self.token)):
            self.token = self.source()
        return self.token

    def renewed(self) -> str | None:
        """A fresh token if the current one is due for renewal (only with a function); else None."""
        if callable(self.source) and self.token is not None and _expiring(self.token):
            return self.current()
        return None

    def auth_flow(self, request: httpx.Request) -> Generator[httpx.Request, httpx.Response, None]:
        token = self.current()
        if token:
            request.headers["Authorization"] = f"Bearer {token}"
        yield request


def _expiring(token: str) -> bool:
    """Whether a JWT's ``exp`` is within RENEW_SECONDS (a token that is not a JWT never is)."""
    try:
        payload = token.split(".")[1]
        claims = json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))
        return float(claims["exp"]) - time.time() < RENEW_SECONDS
    except (IndexError, ValueError, KeyError, TypeError):
        return False


class _Routes:
    """The routes, each a method; ``_call`` sends (sync in Client, a coroutine in AsyncClient)."""

    url: str
    token: Token

    def _call(
        self, method: str, path: str, decode: Callable[[httpx.Response], Any] = _json, **kwargs: Any
    ) -> Any:
        raise NotImplementedError

    # -- the server --

    def health(self) -> dict:
        """``{"status": "ok", "store": ..., "reachable": true}`` when the server is up (no token
        needed); ``"degraded"`` when it cannot reach its store."""
        return self._call("GET", "/health")

    def stats(self) -> dict:
        """What the answering worker holds: open documents, bytes against the budget, opens,
        hits, evictions (``GET /stats``)."""
        return self._call("GET", "/stats")

    def supports_replace(self) -> bool:
        """Whether the server's import route takes ``mode=replace`` (from its OpenAPI schema:
        a server without it would ignore the parameter and upsert)."""

        def decode(response: httpx.Response) -> bool:
            route = response.json().get("paths", {}).get("/documents/{doc}/items", {}).get("post", {})
            return any(
                p.get("name") == "mode" and p.get("in") == "query" and '"replace"' in json.dumps(p)
                for p in route.get("parameters", [])
            )

        return self._call("GET", "/openapi.json", decode)

    # -- documents --

    def documents(self) -> list[dict]:
        """Every document the token reads, oldest first: ``[{"id", "name", "version", "items",
        "bounds"}, ...]``, the server's pages joined."""
        return self._call("GET", "/documents", _page)

    def create_document(self, name: str) -> dict:
        """A new, empty document named ``name``: its metadata, ``id`` among it."""
        return self._call("POST", "/documents", json={"name": name})

    def describe(self, doc: str) -> dict:
        """One document's metadata: ``{"id", "name", "version", "items", "bounds", ...}``."""
        return self._call("GET", f"/documents/{_seg(doc)}")

    document = describe

    def delete_document(self, doc: str) -> None:
        """Delete a document and all its items (its open streams close with 4404)."""
        return self._call("DELETE", f"/documents/{_seg(doc)}", _nothing)

    # -- items --

    def get_item(self, doc: str, item: str) -> dict:
        """One item by id (404 if the document has none by that id)."""
        return self._call("GET", f"/documents/{_seg(doc)}/items/{_seg(item)}")

    def put_item(self, doc: str, item: dict, id: str | None = None) -> dict:
        """Create or replace one whole item (``id`` defaults to ``item["id"]``): ``{"id", "version"}``."""
        key = id if id is not None else item["id"]
        return self._call("PUT", f"/documents/{_seg(doc)}/items/{_seg(key)}", json=item)

    def patch_item(self, doc: str, item: str, fields: dict) -> dict:
        """Change some fields of one item, keeping the others (``"data": None`` drops its data):
        ``{"id", "version"}``."""
        return self._call("PATCH", f"/documents/{_seg(doc)}/items/{_seg(item)}", json=fields)

    def delete_item(self, doc: str, item: str) -> dict:
        """Delete one item: ``{"id", "version"}``."""
        return self._call("DELETE", f"/documents/{_seg(doc)}/items/{_seg(item)}")

    def delete_items(self, doc: str, ids: Iterable[str]) -> dict:
        """Delete many items as one version, all or nothing (a missing id is a 404 naming it):
        ``{"deleted", "version"}``."""
        return self._call("DELETE", f"/documents/{_seg(doc)}/items", json={"ids": list(ids)})

    # -- queries --

    def viewport(
        self,
        doc: str,
        rect: Rect,
        *,
        scale: float | None = None,
        min_px: float | None = None,
        limit: int | None = None,
        min_version: int | None = None,
    ) -> dict:
        """Items touching ``rect`` (x0, y0, x1, y1). With ``scale`` (pixels per canvas unit) and
        ``min_px``, at a level of detail: items of at least ``min_px`` pixels and aggregates
        (``agg``) standing in for the smaller ones. ``{"version", "band", "count",
        "aggregates", "omitted_small", "truncated", "items"}``. With ``min_version`` (the
        version a write answered, say), never an older one: a replica behind it answers 503."""
        x0, y0, x1, y1 = rect
        params = _params(
            x0=x0, y0=y0, x1=x1, y1=y1, scale=scale, min_px=min_px, limit=limit, min_version=min_version
        )
        return self._call("GET", f"/documents/{_seg(doc)}/viewport", params=params)

    def diff(
        self,
        doc: str,
        from_: Rect,
        to: Rect,
        *,
        scale: float | None = None,
        min_px: float | None = None,
        limit: int | None = None,
        from_scale: float | None = None,
        from_band: int | None = None,
        since: int | None = None,
        min_version: int | None = None,
    ) -> dict:
        """What entered and left panning from ``from_`` to ``to`` (stateless): ``{"version",
        "band", "reset", "entered", "truncated", "leave", "enter"}``. ``from_scale`` when
        zooming, ``from_band`` the ``band`` of the answer held, ``since`` the version held
        (items edited after it come too), ``min_version`` as for :meth:`viewport`. ``reset``:
        drop what you hold, take ``enter``."""
        params = _params(
            scale=scale,
            min_px=min_px,
            limit=limit,
            from_scale=from_scale,
            from_band=from_band,
            since=since,
            min_version=min_version,
        )
        params = {"from": _rect(from_), "to": _rect(to), **params}
        return self._call("GET", f"/documents/{_seg(doc)}/diff", params=params)

    def search(self, doc: str, q: str, limit: int | None = None) -> dict:
        """Where the text holds ``q`` (a word or a phrase, folded as the server folds it), in
        document order: ``{"version", "count", "more", "cursor", "total", "total_exact", "hits":
        [{"ids", "box", "boxes", "text"}], "items"}``; ``boxes``: one a line a hit covers."""
        return self._call("GET", f"/documents/{_seg(doc)}/search", params=_params(q=q, limit=limit))

    def cells(self, doc: str, rect: Rect, limit: int | None = None) -> dict:
        """The index's nodes touching ``rect``, shallowest first: ``{"version", "cells": [{"depth",
        "box", "leaf"}, ...]}`` (for seeing the structure)."""
        x0, y0, x1, y1 = rect
        params = _params(x0=x0, y0=y0, x1=x1, y1=y1, limit=limit)
        return self._call("GET", f"/documents/{_seg(doc)}/cells", params=params)


class Client(_Routes):
    """The service's HTTP API over httpx, one method a route; a refusal raises
    :class:`VantageError`. ``token`` goes in ``Authorization: Bearer``: a string, or a function
    returning a fresh signed token, called again a minute before the last one expires."""

    def __init__(
        self, url: str, token: Token = None, timeout: float = 300.0, part_bytes: int = PART_BYTES
    ) -> None:
        self.url, self.token, self.part_bytes = url.rstrip("/"), token, part_bytes
        self.http = httpx.Client(base_url=self.url, auth=_Bearer(token), timeout=timeout)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    def _call(
        self, method: str, path: str, decode: Callable[[httpx.Response], Any] = _json, **kwargs: Any
    ) -> Any:
        answer = decode(_checked(self.http.request(method, path, **kwargs)))
        if isinstance(answer, _Next):  # a list's pages, followed (the rest by the call itself)
            answer = [*answer, *self._call("GET", answer.url, decode)]
        return answer

    def import_items(self, doc: str, source: Any, *, replace: bool = False, gzip: bool = False) -> dict:
        """Bulk import, all or nothing, streamed (the body never sits in memory whole):
        ``{"imported", "version"}``.

        ``source``: a path (NDJSON or a JSON array, gzip'd or not: sent as it is on disk), bytes,
        a binary file, or an iterable of items (dicts) or lines (str or bytes, one line each).
        ``replace``: the document holds exactly these items after (``mode=replace``; else
        upsert by id). ``gzip``: compress the body on the way (``Content-Encoding: gzip``).
        If the iterable raises, the upload is aborted and the server stores nothing. A body
        past ``part_bytes`` goes as an upload of parts of that size (see :meth:`_send`).
        """
        content, headers, _ = _upload(source, gzip)
        return self._send(doc, content, headers, replace)

    def _send(
        self, doc: str, content: bytes | Iterable[bytes], headers: dict[str, str], replace: bool
    ) -> dict:
        """Import ``content``: in one body, or, past ``part_bytes``, as an upload (``POST
        .../uploads``, each part ``PUT`` as it fills, tried up to PART_TRIES times, then the
        commit), which no body cap limits; one part is held in memory at a time."""
        path = f"/documents/{_seg(doc)}"
        parts = _parts([content] if isinstance(content, bytes) else content, self.part_bytes)
        first, second = next(parts, b""), next(parts, None)
        if second is None:
            params = {"mode": "replace"} if replace else None
            try:
                return self._call("POST", f"{path}/items", content=first, headers=headers, params=params)
            except VantageError as error:
                if not _too_big_a_body(error):
                    raise
            # a gzip body that inflates past one body's cap: an upload takes it
        upload = self._call("POST", f"{path}/uploads", json=_upload_options(headers, replace))["id"]
        try:
            count = 0
            for count, part in enumerate(itertools.chain([first], [second] if second else [], parts), 1):
                for attempt in range(PART_TRIES):
                    try:
                        self._call("PUT", f"{path}/uploads/{upload}/parts/{count}", content=part)
                        break
                    except httpx.TransportError:
                        if attempt == PART_TRIES - 1:
                            raise
            return self._call("POST", f"{path}/uploads/{upload}/commit", json={"parts": count})
        except BaseException:
            with contextlib.suppress(Exception):  # nothing was imported: leave nothing behind
                self._call("DELETE", f"{path}/uploads/{upload}", _nothing)
            raise

    def import_stream(
        self, doc: str, chunks: Iterable[bytes], replace: bool = False, gzip: bool = False
    ) -> dict:
        """Bulk import NDJSON sent as ``chunks`` come, as they are (a chunk need not end a
        line); see :meth:`import_items`."""
        content: Iterable[bytes] = _zipped(chunks) if gzip else chunks
        headers = {**NDJSON, "content-encoding": "gzip"} if gzip else dict(NDJSON)
        return self._send(doc, content, headers, replace)

    def export_lines(self, doc: str) -> Iterator[bytes]:
        """Every item as an NDJSON line, streamed (what an import takes back)."""
        with self.http.stream("GET", f"/documents/{_seg(doc)}/items") as response:
            _checked(response)
            for line in response.iter_lines():
                if line:
                    yield line.encode()

    def export(self, doc: str) -> Iterator[dict]:
        """Every item of ``doc``, streamed: ``for item in client.export(doc)``."""
        for line in self.export_lines(doc):
            yield json.loads(line)

    def stream(
        self,
        doc: str,
        *,
        scale: float | None = None,
        min_px: float = 0.0,
        limit: int | None = None,
        min_version: int | None = None,
    ) -> Stream:
        """The pan stream of ``doc``, opened (use it in ``with``); see :class:`Stream`."""
        return Stream(
            self.url, doc, self.token, scale=scale, min_px=min_px, limit=limit, min_version=min_version
        )


class AsyncClient(_Routes):
    """:class:`Client` over ``httpx.AsyncClient``: the same methods, awaited; ``export`` is an
    async iterator, and an import also takes an async iterable of items or lines."""

    def __init__(
        self, url: str, token: Token = None, timeout: float = 300.0, part_bytes: int = PART_BYTES
    ) -> None:
        self.url, self.token, self.part_bytes = url.rstrip("/"), token, part_bytes
        self.http = httpx.AsyncClient(base_url=self.url, auth=_Bearer(token), timeout=timeout)

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self.http.aclose()

    async def _call(
        self, method: str, path: str, decode: Callable[[httpx.Response], Any] = _json, **kwargs: Any
    ) -> Any:
        answer = decode(await _checked_async(await self.http.request(method, path, **kwargs)))
        if isinstance(answer, _Next):  # a list's pages, followed (the rest by the call itself)
            answer = [*answer, *await self._call("GET", answer.url, decode)]
        return answer

    async def import_items(self, doc: str, source: Any, *, replace: bool = False, gzip: bool = False) -> dict:
        """As :meth:`Client.import_items`; ``source`` may also be an async iterable of items or lines."""
        if isinstance(source, AsyncIterable):
            content: Any = _alines(source, gzip)
            headers = {**NDJSON, "content-encoding": "gzip"} if gzip else dict(NDJSON)
        else:
            content, headers, _ = await asyncio.to_thread(_upload, source, gzip)
            if not isinstance(content, bytes):
                content = _aiter(content)
        return await self._send(doc, content, headers, replace)

    async def import_stream(
        self, doc: str, chunks: Iterable[bytes], replace: bool = False, gzip: bool = False
    ) -> dict:
        """As :meth:`Client.import_stream`."""
        content = _aiter(_zipped(chunks) if gzip else chunks)
        headers = {**NDJSON, "content-encoding": "gzip"} if gzip else dict(NDJSON)
        return await self._send(doc, content, headers, replace)

    async def _send(
        self, doc: str, content: bytes | AsyncIterable[bytes], headers: dict[str, str], replace: bool
    ) -> dict:
        """As :meth:`Client._send`."""
        path = f"/documents/{_seg(doc)}"
        parts = _aparts(_aiter([content]) if isinstance(content, bytes) else content, self.part_bytes)
        first, second = await anext(parts, b""), await anext(parts, None)
        if second is None:
            params = {"mode": "replace"} if replace else None
            try:
                return await self._call(
                    "POST", f"{path}/items", content=first, headers=headers, params=params
                )
            except VantageError as error:
                if not _too_big_a_body(error):
                    raise
            # a gzip body that inflates past one body's cap: an upload takes it
        upload = (await self._call("POST", f"{path}/uploads", json=_upload_options(headers, replace)))["id"]

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
                        await self._call("PUT", f"{path}/uploads/{upload}/parts/{count}", content=part)
                        break
                    except httpx.TransportError:
                        if attempt == PART_TRIES - 1:
                            raise
            return await self._call("POST", f"{path}/uploads/{upload}/commit", json={"parts": count})
        except BaseException:
            with contextlib.suppress(Exception):  # nothing was imported: leave nothing behind
                await self._call("DELETE", f"{path}/uploads/{upload}", _nothing)
            raise

    async def export_lines(self, doc: str) -> AsyncIterator[bytes]:
        """Every item as an NDJSON line, streamed."""
        async with self.http.stream("GET", f"/documents/{_seg(doc)}/items") as response:
            await _checked_async(response)
            async for line in response.aiter_lines():
                if line:
                    yield line.encode()

    async def export(self, doc: str) -> AsyncIterator[dict]:
        """Every item of ``doc``, streamed: ``async for item in client.export(doc)``."""
        async for line in self.export_lines(doc):
            yield json.loads(line)

    def stream(
        self,
        doc: str,
        *,
        scale: float | None = None,
        min_px: float = 0.0,
        limit: int | None = None,
        min_version: int | None = None,
    ) -> AsyncStream:
        """The pan stream of ``doc``: ``async with client.stream(doc) as s``; see :class:`AsyncStream`."""
        return AsyncStream(
            self.url, doc, self.token, scale=scale, min_px=min_px, limit=limit, min_version=min_version
        )


# -- the stream ----------------------------------------------------------------------------------

CLOSES = {1008: 408, 1013: 503}  # close codes that are not 4000 + an HTTP status
GRACE = 0.5  # seconds to wait, after an error message, for the close that may follow it


class _Held:
    """What a stream's client holds: the answers applied as the page does (``reset`` drops
    everything, then ``leave``, then ``enter`` upserts)."""

    def __init__(
        self,
        url: str,
        doc: str,
        token: Token,
        scale: float | None,
        min_px: float,
        limit: int | None,
        min_version: int | None = None,
    ) -> None:
        base = url.rstrip("/")
        base = "ws" + base[4:] if base.startswith("http") else base
        self.tokens = _Bearer(token)
        query = urlencode(_params(token=self.tokens.current(), min_version=min_version))
        self.url = f"{base}/documents/{_seg(doc)}/stream" + (f"?{query}" if query else "")
        self.doc, self.scale, self.min_px, self.limit = doc, scale, min_px, limit
        self.items: dict[str, dict] = {}  # id -> item: what is on screen (aggregates too)
        self.version = 0  # the document version the items reflect
        self.band: int | None = None  # the zoom band of the aggregates held (None: real items only)
        self.truncated = False
        self.seq = 0  # the last viewport sent
        self.answered = 0  # the seq of the last view answered
        self.errors: list[str] = []  # error messages received

    def _messages(
        self, rect: Rect, scale: float | None, min_px: float | None, limit: int | None
    ) -> list[str]:
        """A viewport's message, after the stream's fresh token when the last is about to expire."""
        fresh = self.tokens.renewed()
        renewal = [json.dumps({"token": fresh})] if fresh else []
        return [*renewal, self._message(rect, scale, min_px, limit)]

    def _message(self, rect: Rect, scale: float | None, min_px: float | None, limit: int | None) -> str:
        self.seq += 1
        message: dict[str, Any] = {"seq": self.seq, "viewport": [float(v) for v in rect]}
        scale = self.scale if scale is None else scale
        min_px = self.min_px if min_px is None else min_px
        limit = self.limit if limit is None else limit
        if scale is not None:
            message["scale"] = scale
        if min_px:
            message["min_px"] = min_px
        if limit is not None:
            message["limit"] = limit
        return json.dumps(message)

    def _apply(self, text: str | bytes) -> dict:
        answer = json.loads(text)
        if answer.get("type") == "error":
            self.errors.append(answer.get("message", ""))
            return answer
        if answer.get("reset"):
            self.items.clear()
        for key in answer["leave"]:
            self.items.pop(key, None)
        for item in answer["enter"]:
            self.items[item["id"]] = item
        self.version = answer["version"]
        if answer["type"] == "view":
            self.band, self.truncated = answer.get("band"), answer.get("truncated", False)
            self.answered = max(self.answered, answer["seq"])
        return answer

    def _closed(self, error: Exception) -> VantageError:
        received = getattr(error, "rcvd", None)
        code = received.code if received is not None else 1006
        reason = self.errors[-1] if self.errors else (received.reason if received is not None else "")
        status = code - 4000 if 4000 <= code < 5000 else CLOSES.get(code, 503)
        return VantageError.made(status, reason or f"the stream closed (code {code})", self.url)

    def _refused(self, error: Exception) -> VantageError:
        response = getattr(error, "response", None)
        if response is None:
            return VantageError.made(503, f"cannot open the stream: {error}", self.url)
        body = bytes(response.body or b"").decode(errors="replace")
        try:
            detail = json.loads(body)["detail"]
        except Exception:
            detail = body[:500] or f"the handshake was refused ({response.status_code})"
        return VantageError.made(response.status_code, detail, self.url)


class Stream(_Held):
    """A document's pan stream (``WS /documents/{doc}/stream``, websockets' sync client):
    send viewports, get what entered and left; ``items`` holds what is in view, kept from the
    answers and from the edits others make, which the server pushes.

    ::

        with Stream(url, doc, scale=0.5, min_px=1) as stream:
            stream.view((0, 0, 1920, 1080))   # sends, waits for its answer: stream.items is the view
            stream.send((0, 40, 1920, 1120))  # or send as you pan and read answers as they come:
            for answer in stream:             # each applied to stream.items before it is yielded
                ...

    A viewport sent while an older one still waits replaces it (the server answers the latest,
    ``seq`` says which). A refused or closed stream raises :class:`VantageError` (4404: no such
    document -> status 404; 4401/4403: token -> 401/403). With ``min_version``, its first answer
    is of that version or later (4409 -> 409: never written; 1013 -> 503: try again).
    """

    def __init__(
        self,
        url: str,
        doc: str,
        token: Token = None,
        *,
        scale: float | None = None,
        min_px: float = 0.0,
        limit: int | None = None,
        min_version: int | None = None,
        open_timeout: float = 30.0,
    ) -> None:
        from websockets.exceptions import InvalidHandshake
        from websockets.sync.client import connect

        super().__init__(url, doc, token, scale, min_px, limit, min_version)
        try:
            # entered: the connection itself (websockets >= 17.1 warns when connect() is used bare)
            self.ws = connect(self.url, open_timeout=open_timeout, max_size=None, proxy=None).__enter__()
        except InvalidHandshake as error:
            raise self._refused(error) from None
        except OSError as error:
            raise VantageError.made(503, f"cannot reach {self.url}: {error}", self.url) from None

    def __enter__(self) -> Stream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.ws.close()

    def send(
        self, rect: Rect, *, scale: float | None = None, min_px: float | None = None, limit: int | None = None
    ) -> int:
        """Send a viewport (the stream's ``scale``, ``min_px`` and ``limit`` unless given); its seq."""
        from websockets.exceptions import ConnectionClosed

        try:
            for message in self._messages(rect, scale, min_px, limit):
                self.ws.send(message)
        except ConnectionClosed as error:
            raise self._closed(error) from None
        return self.seq

    def receive(self, timeout: float | None = None) -> dict | None:
        """The next answer (a view, an edit pushed, or an error), applied to ``items``; None
        after ``timeout`` seconds without one.

        :raises VantageError: if the stream closes (with the status of its close code)
        """
        from websockets.exceptions import ConnectionClosed

        try:
            text = self.ws.recv(timeout)
        except TimeoutError:
            return None
        except ConnectionClosed as error:
            raise self._closed(error) from None
        return self._apply(text)

    def view(
        self,
        rect: Rect,
        *,
        scale: float | None = None,
        min_px: float | None = None,
        limit: int | None = None,
        timeout: float = 60.0,
    ) -> dict:
        """Send a viewport and wait for its answer (applying whatever comes before it): the
        answer; ``items`` is then the view.

        :raises VantageError: 422 if the server refused the viewport, or the stream closed
        :raises TimeoutError: no answer within ``timeout`` seconds
        """
        seq = self.send(rect, scale=scale, min_px=min_px, limit=limit)
        deadline = time.monotonic() + timeout
        while True:
            answer = self.receive(max(0.0, deadline - time.monotonic()))
            if answer is None:
                raise TimeoutError(f"no answer to viewport {seq} within {timeout:g} s")
            if answer["type"] == "error":
                self.receive(GRACE)  # a refusal closes the stream next: raises with its status
                raise VantageError.made(422, answer.get("message", ""), self.url)
            if answer["type"] == "view" and answer["seq"] >= seq:
                return answer

    def __iter__(self) -> Iterator[dict]:
        """Answers as they come, applied, until the server closes the stream normally."""
        from websockets.exceptions import ConnectionClosed, ConnectionClosedOK

        while True:
            try:
                text = self.ws.recv()
            except ConnectionClosedOK:
                return
            except ConnectionClosed as error:
                raise self._closed(error) from None
            yield self._apply(text)


class AsyncStream(_Held):
    """:class:`Stream` over websockets' asyncio client: ``async with AsyncStream(...) as s``
    (or ``await s.open()``), then ``await s.view(rect)``, ``s.send``, ``await s.receive()``,
    ``async for answer in s``."""

    def __init__(
        self,
        url: str,
        doc: str,
        token: Token = None,
        *,
        scale: float | None = None,
        min_px: float = 0.0,
        limit: int | None = None,
        min_version: int | None = None,
        open_timeout: float = 30.0,
    ) -> None:
        super().__init__(url, doc, token, scale, min_px, limit, min_version)
        self.open_timeout = open_timeout
        self.ws: Any = None

    async def open(self) -> AsyncStream:
        from websockets.asyncio.client import connect
        from websockets.exceptions import InvalidHandshake

        try:
            self.ws = await connect(self.url, open_timeout=self.open_timeout, max_size=None, proxy=None)
        except InvalidHandshake as error:
            raise self._refused(error) from None
        except OSError as error:
            raise VantageError.made(503, f"cannot reach {self.url}: {error}", self.url) from None
        return self

    async def __aenter__(self) -> AsyncStream:
        return await self.open()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        if self.ws is not None:
            await self.ws.close()

    async def send(
        self, rect: Rect, *, scale: float | None = None, min_px: float | None = None, limit: int | None = None
    ) -> int:
        """Send a viewport; its seq."""
        from websockets.exceptions import ConnectionClosed

        try:
            for message in self._messages(rect, scale, min_px, limit):
                await self.ws.send(message)
        except ConnectionClosed as error:
            raise self._closed(error) from None
        return self.seq

    async def receive(self, timeout: float | None = None) -> dict | None:
        """The next answer, applied; None after ``timeout`` seconds without one."""
        from websockets.exceptions import ConnectionClosed

        try:
            async with asyncio.timeout(timeout):
                text = await self.ws.recv()
        except TimeoutError:
            return None
        except ConnectionClosed as error:
            raise self._closed(error) from None
        return self._apply(text)

    async def view(
        self,
        rect: Rect,
        *,
        scale: float | None = None,
        min_px: float | None = None,
        limit: int | None = None,
        timeout: float = 60.0,
    ) -> dict:
        """Send a viewport and wait for its answer; see :meth:`Stream.view`."""
        seq = await self.send(rect, scale=scale, min_px=min_px, limit=limit)
        deadline = time.monotonic() + timeout
        while True:
            answer = await self.receive(max(0.0, deadline - time.monotonic()))
            if answer is None:
                raise TimeoutError(f"no answer to viewport {seq} within {timeout:g} s")
            if answer["type"] == "error":
                await self.receive(GRACE)
                raise VantageError.made(422, answer.get("message", ""), self.url)
            if answer["type"] == "view" and answer["seq"] >= seq:
                return answer

    async def __aiter__(self) -> AsyncIterator[dict]:
        """Answers as they come, applied, until the server closes the stream normally."""
        from websockets.exceptions import ConnectionClosed, ConnectionClosedOK

        while True:
            try:
                text = await self.ws.recv()
            except ConnectionClosedOK:
                return
            except ConnectionClosed as error:
                raise self._closed(error) from None
            yield self._apply(text)
