"""The hot path: ``GET /documents/{doc}/viewport``, ``/diff`` and ``/tiles/...`` without the
framework's per-request work, as an ASGI layer around the app.

A pan sends one of these per frame (a zoomed-out screen a dozen tile requests), and the answer
itself (an index diff and a join of pre-encoded JSON) takes a fraction of what routing,
dependency solving, pydantic validation and five middlewares take around it. :class:`HotRoutes` answers a plainly valid request the way the
full stack would, with the same pieces: the guard's own admission check, the same answer
functions the routes call, the document handled as ``deps._document`` handles it (caught up with
the store, pinned while the answer is built and sent), and gzip as ``GZipMiddleware`` does it.
Each route's query parameters are read from the route's own declaration (:meth:`HotRoute.of`),
so they are declared once. Anything else (another route or method, a missing, repeated or odd
parameter, a value out of range, a refused request, a browser origin when CORS is on, any error
while answering) goes on to the full stack, which answers it as it always did: every validation
message and error comes from there.
"""

from __future__ import annotations

import inspect
import operator
import re
import types
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial
from typing import Annotated, Any, get_args, get_origin, get_type_hints
from urllib.parse import parse_qsl

import annotated_types
from fastapi import params
from fastapi.concurrency import run_in_threadpool
from starlette.middleware.gzip import GZipResponder
from starlette.types import ASGIApp, Receive, Scope, Send

from .documents import Document
from .guard import Guard
from .registry import Registry
from .responses import GZIP_LEVEL
from .tiles import Prepared

__all__ = ["HotRoute", "HotRoutes", "answered"]

# Query values the fast path converts itself: forms pydantic parses to the same number as
# float() and int() do. Anything else (blank, "nan", "1_0", a duplicate...) goes to FastAPI.
_FLOAT = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d{1,4})?")
_INT = re.compile(r"[-+]?\d{1,18}")
_PLAIN = "0123456789.+-"  # a decimal without exponent: float() takes exactly what _FLOAT does
_JSON = b"application/json"


class _Slow(Exception):
    """This request is for the full route: FastAPI validates it and words the 422."""


def _float(text: str) -> float:
    if text and not text.strip(_PLAIN):  # the common form, told apart without the regex
        try:
            return float(text)
        except ValueError:
            raise _Slow from None
    if _FLOAT.fullmatch(text) is None:
        raise _Slow
    return float(text)


def _int(text: str) -> int:
    if _INT.fullmatch(text) is None:
        raise _Slow
    return int(text)


def _bool(text: str) -> bool:
    if text in ("true", "1"):
        return True
    if text in ("false", "0"):
        return False
    raise _Slow  # pydantic's other spellings ("yes", "on", "T"...) and its 422


_PARSERS: dict[type, Callable[[str], Any]] = {float: _float, int: _int, str: str, bool: _bool}
# A bound of Query(...) (annotated_types' metadata) and the test a value must pass.
_BOUNDS: dict[type, tuple[str, Callable[[Any, Any], bool]]] = {
    annotated_types.Gt: ("gt", operator.gt),
    annotated_types.Ge: ("ge", operator.ge),
    annotated_types.Lt: ("lt", operator.lt),
    annotated_types.Le: ("le", operator.le),
}


def _converter(kind: type, bounds: list[tuple[Callable[[Any, Any], bool], Any]]) -> Callable[[str], Any]:
    parse = _PARSERS[kind]
    if not bounds:
        return parse

    def convert(text: str) -> Any:
        value = parse(text)
        for passes, limit in bounds:
            if not passes(value, limit):  # NaN never gets here: _float refuses its spelling
                raise _Slow
        return value

    return convert


@dataclass(frozen=True)
class HotRoute:
    """One route the fast path answers: its answer function (the one the route calls) and, by
    query name, the keyword argument and converter of each parameter."""

    answer: Callable[..., bytes]
    required: frozenset[str]
    converters: Mapping[str, tuple[str, Callable[[str], Any]]]

    @classmethod
    def of(cls, endpoint: Callable[..., Any], answer: Callable[..., bytes]) -> HotRoute:
        """The fast path of ``endpoint``, from its declared ``Query`` parameters: each one's
        name (or alias), type and bounds. Dependencies (``Depends``) are left to the layer.

        :raises TypeError: if a parameter is declared in a way the fast path cannot copy
        """
        required, converters = set(), {}
        hints = get_type_hints(endpoint, include_extras=True)
        for name, parameter in inspect.signature(endpoint).parameters.items():
            hint = hints[name]
            extras = get_args(hint)[1:] if get_origin(hint) is Annotated else ()
            if any(isinstance(e, params.Depends) for e in extras):
                continue
            query = next((e for e in extras if isinstance(e, params.Query)), None)
            if query is None:
                raise TypeError(f"{endpoint.__name__}({name}): not a Query parameter")
            kinds = [
                t for t in get_args(get_args(hint)[0]) or (get_args(hint)[0],) if t is not types.NoneType
            ]
            if len(kinds) != 1 or kinds[0] not in _PARSERS:
                raise TypeError(f"{endpoint.__name__}({name}): of a type the fast path does not parse")
            bounds = []
            for rule in query.metadata:
                bound = _BOUNDS.get(type(rule))
                if bound is None:
                    raise TypeError(
                        f"{endpoint.__name__}({name}): {rule!r} is not a bound the fast path checks"
                    )
                field, passes = bound
                bounds.append((passes, getattr(rule, field)))
            key = query.alias or name
            converters[key] = (name, _converter(kinds[0], bounds))
            if parameter.default is inspect.Parameter.empty:
                required.add(key)
        return cls(answer, frozenset(required), converters)

    def arguments(self, raw: bytes) -> dict[str, Any]:
        """The answer function's keyword arguments from the query string ``raw``, as FastAPI
        would validate them (``min_version`` among them).

        :raises _Slow: unless every parameter is present once and plainly valid
        """
        kwargs: dict[str, Any] = {}
        seen = set()
        for name, value in _query(raw):
            if name in seen:
                raise _Slow  # FastAPI takes the last; not worth copying
            seen.add(name)
            converter = self.converters.get(name)
            if converter is not None:
                kwargs[converter[0]] = converter[1](value)
        if not self.required <= seen:
            raise _Slow
        return kwargs


def _query(raw: bytes) -> list[tuple[str, str]]:
    """``raw`` split as Starlette's ``QueryParams`` splits it."""
    text = raw.decode("latin-1")
    if "%" in text or "+" in text:
        return parse_qsl(text, keep_blank_values=True)
    pairs = []
    for part in text.split("&"):
        if part:
            name, _, value = part.partition("=")
            pairs.append((name, value))
    return pairs


async def answered(answer: Callable[..., bytes], *args: Any, **kwargs: Any) -> bytes:
    """``answer(*args, **kwargs)``, the hot routes' answer function, where it is cheapest: at
    a level of detail (``scale`` and ``min_px``) in a worker thread, as aggregates' masks take
    milliseconds (up to ~0.1 s for a million specks in view); else here, as a page-level
    answer takes less than the hop. The routes and the fast path both call it."""
    if kwargs.get("scale") and kwargs.get("min_px"):
        return await run_in_threadpool(partial(answer, *args, **kwargs))
    return answer(*args, **kwargs)


class HotRoutes:
    """The ASGI layer: answers ``GET /documents/{doc}/<name>`` for each of ``routes`` when it
    can, and hands everything else to ``app``. Around the app's whole middleware stack
    (``main.create_app``), so the guard, CORS and gzip it copies are all inside it. ``state`` is the app's: its settings,
    access and (once started) registry."""

    def __init__(
        self, app: ASGIApp, state: Any, routes: Mapping[str, HotRoute], tile: Callable[..., Any] | None = None
    ) -> None:
        self.app, self.state, self.routes, self.tile_answered = app, state, routes, tile
        settings = state.settings
        self.admit = Guard(app, settings, state.access).admit
        self.gzip_min_bytes: int | None = settings.gzip_min_bytes
        self.cors = bool(settings.origins)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if not await self.answer(scope, receive, send):
            await self.app(scope, receive, send)

    async def answer(self, scope: Scope, receive: Receive, send: Send) -> bool:
        """Answer the request; False (nothing sent) when the full stack should."""
        if scope["type"] != "http" or scope["method"] != "GET" or scope.get("root_path"):
            return False
        path: str = scope["path"]
        if not path.startswith("/documents/"):
            return False
        doc_id, _, name = path[11:].partition("/")
        if name.startswith("tiles/") and doc_id and self.tile_answered is not None:
            return await self.tile(scope, send, doc_id, name[6:])
        route = self.routes.get(name)
        if not doc_id or route is None:
            return False
        encoding = None
        for header, value in scope["headers"]:
            if header == b"accept-encoding":
                if encoding is None:  # the first, as Starlette's Headers.get reads it
                    encoding = value
            elif header == b"origin" and self.cors:
                return False  # CORSMiddleware adds its headers
        try:
            kwargs = route.arguments(scope["query_string"])
        except Exception:  # _Slow: FastAPI validates it and words the 422
            return False
        doc = await self._admitted(scope, doc_id, kwargs.pop("min_version", None))
        if doc is None:
            return False
        registry: Registry = self.state.registry
        with registry.pinned(doc):
            try:
                body = await answered(route.answer, doc, self.state.settings, **kwargs)
            except Exception:  # a 409 or 422 (or a bug): the route raises it again and answers it
                return False
            headers = [(b"content-length", str(len(body)).encode()), (b"content-type", _JSON)]
            start = {"type": "http.response.start", "status": 200, "headers": headers}
            message = {"type": "http.response.body", "body": body}
            minimum = self.gzip_min_bytes
            if minimum is None or len(body) < minimum:  # GZipMiddleware passes these through
                await send(start)
                await send(message)
            elif encoding is None or b"gzip" not in encoding:
                headers.append((b"vary", b"Accept-Encoding"))  # as GZipMiddleware marks them
                await send(start)
                await send(message)
            elif isinstance(body, Prepared):  # gzipped once already, for every client
                headers[0] = (b"content-length", str(len(body.gzipped)).encode())
                headers += [(b"vary", b"Accept-Encoding"), (b"content-encoding", b"gzip")]  # in its order
                await send(start)
                await send({"type": "http.response.body", "body": body.gzipped})
            else:

                async def respond(scope: Scope, receive: Receive, send: Send) -> None:
                    await send(start)
                    await send(message)

                await GZipResponder(respond, minimum, compresslevel=GZIP_LEVEL)(scope, receive, send)
        return True

    async def _admitted(self, scope: Scope, doc_id: str, version: int | None) -> Document | None:
        """The document, once the guard admits the request, open and at ``version`` or later;
        None when the full stack should answer (it words a refusal or a 404, or it waits for
        the version)."""
        try:
            self.admit(scope)
        except Exception:  # the guard's refusal
            return None
        registry: Registry = self.state.registry
        try:
            doc = await registry.get(doc_id)
        except Exception:  # a 404, or the store failing
            return None
        return None if version is not None and version > doc.snapshot.version else doc

    async def tile(self, scope: Scope, send: Send, doc_id: str, where: str) -> bool:
        """Answer ``GET /documents/{doc}/tiles/{band}/{z}/{tx}/{ty}`` as its route does (a
        browser fetches a screen's tiles at once: a dozen requests); False when it should."""
        answered = self.tile_answered
        assert answered is not None  # asked only when given
        parts = where.split("/")
        if len(parts) != 4 or not all(_INT.fullmatch(p) for p in parts):
            return False
        band, z, tx, ty = map(int, parts)
        version = None
        for name, value in _query(scope["query_string"]):
            if name == "version":
                if version is not None or _INT.fullmatch(value) is None or int(value) < 0:
                    return False  # repeated, or FastAPI's 422
                version = int(value)
        seen: dict[bytes, str] = {}
        for header, value in scope["headers"]:
            if header in (b"if-none-match", b"accept-encoding") and header not in seen:
                seen[header] = value.decode("latin-1")
            elif header == b"origin" and self.cors:
                return False
        doc = await self._admitted(scope, doc_id, version)
        if doc is None:
            return False
        with self.state.registry.pinned(doc):
            try:
                status, headers, body = await answered(
                    doc,
                    self.state.access.reads_private,
                    band,
                    z,
                    tx,
                    ty,
                    version,
                    seen.get(b"if-none-match", ""),
                    seen.get(b"accept-encoding", ""),
                )
            except Exception:  # a 404, 409 or 422: the route raises it again and words it
                return False
            raw = [(k.encode(), v.encode()) for k, v in headers]
            await send({"type": "http.response.start", "status": status, "headers": raw})
            await send({"type": "http.response.body", "body": body})
        return True
