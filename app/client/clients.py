"""The service's HTTP API as Python methods, one a route: :class:`Client` over ``httpx.Client``
and :class:`AsyncClient` over ``httpx.AsyncClient``, the same methods (a test holds their
parameters alike), the async ones real coroutines, so a type checker sees ``await
client.health()`` as the ``dict`` it is.

Imports go through :mod:`app.client.uploads`, streams open :mod:`app.client.streams`; what a
request is (path segments, parameters, pages, errors, the token) comes from :mod:`app.client`.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterable, AsyncIterator, Callable, Iterable, Iterator
from typing import Any

import httpx

from app.client import (
    Rect,
    Token,
    _Bearer,
    _checked,
    _checked_async,
    _json,
    _Next,
    _nothing,
    _page,
    _params,
    _rect,
    _seg,
)
from app.client.streams import AsyncStream, Stream
from app.client.uploads import NDJSON, PART_BYTES, _aiter, _alines, _asend, _send, _upload, _zipped

__all__ = [
    "AsyncClient",
    "Client",
]


def _takes_replace(response: httpx.Response) -> bool:
    """Whether an OpenAPI schema's import route takes ``mode=replace``."""
    route = response.json().get("paths", {}).get("/documents/{doc}/items", {}).get("post", {})
    return any(
        p.get("name") == "mode" and p.get("in") == "query" and '"replace"' in json.dumps(p)
        for p in route.get("parameters", [])
    )


class Client:
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
        return self._call("GET", "/openapi.json", _takes_replace)

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

    # -- imports and exports --

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
        """Import ``content``: in one body, or, past ``part_bytes``, as an upload of parts (see
        :func:`app.client.uploads._send`)."""
        return _send(self._call, doc, content, headers, replace, self.part_bytes)

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


class AsyncClient:
    """:class:`Client` over ``httpx.AsyncClient``: the same methods, each a coroutine to await
    (typed as what it returns once awaited); ``export`` is an async iterator, and an import
    also takes an async iterable of items or lines."""

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

    # -- the server --

    async def health(self) -> dict:
        """As :meth:`Client.health`: ``{"status": "ok", ...}`` when the server is up."""
        return await self._call("GET", "/health")

    async def stats(self) -> dict:
        """As :meth:`Client.stats`: what the answering worker holds."""
        return await self._call("GET", "/stats")

    async def supports_replace(self) -> bool:
        """As :meth:`Client.supports_replace`: whether imports take ``mode=replace``."""
        return await self._call("GET", "/openapi.json", _takes_replace)

    # -- documents --

    async def documents(self) -> list[dict]:
        """As :meth:`Client.documents`: every document the token reads, the pages joined."""
        return await self._call("GET", "/documents", _page)

    async def create_document(self, name: str) -> dict:
        """As :meth:`Client.create_document`."""
        return await self._call("POST", "/documents", json={"name": name})

    async def describe(self, doc: str) -> dict:
        """As :meth:`Client.describe`: one document's metadata."""
        return await self._call("GET", f"/documents/{_seg(doc)}")

    document = describe

    async def delete_document(self, doc: str) -> None:
        """As :meth:`Client.delete_document`."""
        return await self._call("DELETE", f"/documents/{_seg(doc)}", _nothing)

    # -- items --

    async def get_item(self, doc: str, item: str) -> dict:
        """As :meth:`Client.get_item`."""
        return await self._call("GET", f"/documents/{_seg(doc)}/items/{_seg(item)}")

    async def put_item(self, doc: str, item: dict, id: str | None = None) -> dict:
        """As :meth:`Client.put_item`."""
        key = id if id is not None else item["id"]
        return await self._call("PUT", f"/documents/{_seg(doc)}/items/{_seg(key)}", json=item)

    async def patch_item(self, doc: str, item: str, fields: dict) -> dict:
        """As :meth:`Client.patch_item`."""
        return await self._call("PATCH", f"/documents/{_seg(doc)}/items/{_seg(item)}", json=fields)

    async def delete_item(self, doc: str, item: str) -> dict:
        """As :meth:`Client.delete_item`."""
        return await self._call("DELETE", f"/documents/{_seg(doc)}/items/{_seg(item)}")

    async def delete_items(self, doc: str, ids: Iterable[str]) -> dict:
        """As :meth:`Client.delete_items`."""
        return await self._call("DELETE", f"/documents/{_seg(doc)}/items", json={"ids": list(ids)})

    # -- queries --

    async def viewport(
        self,
        doc: str,
        rect: Rect,
        *,
        scale: float | None = None,
        min_px: float | None = None,
        limit: int | None = None,
        min_version: int | None = None,
    ) -> dict:
        """As :meth:`Client.viewport`: items touching ``rect``, at a level of detail."""
        x0, y0, x1, y1 = rect
        params = _params(
            x0=x0, y0=y0, x1=x1, y1=y1, scale=scale, min_px=min_px, limit=limit, min_version=min_version
        )
        return await self._call("GET", f"/documents/{_seg(doc)}/viewport", params=params)

    async def diff(
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
        """As :meth:`Client.diff`: what entered and left panning from ``from_`` to ``to``."""
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
        return await self._call("GET", f"/documents/{_seg(doc)}/diff", params=params)

    async def search(self, doc: str, q: str, limit: int | None = None) -> dict:
        """As :meth:`Client.search`: where the text holds ``q``."""
        return await self._call("GET", f"/documents/{_seg(doc)}/search", params=_params(q=q, limit=limit))

    async def cells(self, doc: str, rect: Rect, limit: int | None = None) -> dict:
        """As :meth:`Client.cells`: the index's nodes touching ``rect``."""
        x0, y0, x1, y1 = rect
        params = _params(x0=x0, y0=y0, x1=x1, y1=y1, limit=limit)
        return await self._call("GET", f"/documents/{_seg(doc)}/cells", params=params)

    # -- imports and exports --

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
        return await _asend(self._call, doc, content, headers, replace, self.part_bytes)

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
