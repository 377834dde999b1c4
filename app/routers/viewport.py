"""Viewport and diff queries: what a client shows, and what changed as it panned.

The two hot routes are declared here for FastAPI (OpenAPI, validation, error messages) and
answered by :class:`HotRoutes` when their query is plainly valid: see there.
"""

import re
from collections.abc import Callable
from typing import Annotated, Any
from urllib.parse import parse_qsl

from fastapi import APIRouter, Query, Response
from starlette.middleware.gzip import GZipResponder
from starlette.types import ASGIApp, Receive, Scope, Send

from .. import answers
from ..answers import Held, View
from ..config import Settings
from ..deps import DocumentDep, RegistryDep, SettingsDep
from ..documents import Document
from ..errors import Conflict, Invalid
from ..examples import ITEM, documented
from ..registry import Registry
from ..responses import JSONBytes
from ..snapshots import Snapshot

__all__ = ["GZIP_LEVEL", "HotRoutes", "router"]

# Level 1: a 89 kB viewport answer shrinks 4.2x in ~0.3 ms (level 9 would take ~12 ms for
# 4.9x); a pan's 4 kB diff 4x in ~10 us. (main's GZipMiddleware uses it too.)
GZIP_LEVEL = 1

router = APIRouter(prefix="/documents/{doc}", tags=["viewport"])
# The routes are async: an answer takes well under a millisecond of compiled work and joins,
# less than a hop to the thread pool and back costs under load.

Scale = Annotated[float | None, Query(gt=0, description="pixels per canvas unit, for level of detail")]
MinPx = Annotated[float, Query(ge=0, description="leave out items smaller than this many pixels")]
Limit = Annotated[int | None, Query(ge=1, description="most items to return (capped by the server)")]
MinVersion = Annotated[
    int | None,
    Query(
        ge=0,
        description="answer at this version or later (a write's answer names it): a replica "
        "behind it catches up, and when it cannot reach its store within VANTAGE_CATCH_UP_MS "
        "answers 503 with Retry-After; a version never written is a 409",
    ),
]


def _view(rect: object, name: str, scale: float | None = None, min_px: float = 0.0) -> View:
    """The library's own validation, as a 422 that says which coordinate is wrong."""
    try:
        return View.of(rect, name, scale, min_px)
    except ValueError as error:
        raise Invalid(str(error)) from None


@router.get(
    "/viewport",
    response_class=JSONBytes,
    responses=documented(
        200,
        {
            "version": 4,
            "band": None,
            "count": 1,
            "aggregates": 0,
            "omitted_small": 0,
            "truncated": False,
            "items": [ITEM],
        },
        404,
        422,
    ),
)
async def read_viewport(
    doc: DocumentDep,
    settings: SettingsDep,
    registry: RegistryDep,
    x0: Annotated[float, Query(examples=[0.0])],
    y0: Annotated[float, Query(examples=[0.0])],
    x1: Annotated[float, Query(examples=[1920.0])],
    y1: Annotated[float, Query(examples=[1080.0])],
    scale: Scale = None,
    min_px: MinPx = 0.0,
    limit: Limit = None,
    min_version: MinVersion = None,
) -> Response:
    """Items whose box touches the viewport (closed intervals), at the client's level of detail.

    ``count`` is how many items are shown in all; ``omitted_small`` how many more the level of
    detail left out; ``truncated`` says ``items`` holds only the first ``limit`` of them.
    """
    await registry.catch_up_to(doc, min_version, settings.catch_up_ms / 1000)
    return JSONBytes(viewport_answer(doc, settings, x0, y0, x1, y1, scale, min_px, limit))


def viewport_answer(
    doc: Document,
    settings: Settings,
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    scale: float | None = None,
    min_px: float = 0.0,
    limit: int | None = None,
) -> bytes:
    """The ``/viewport`` answer for validated parameters.

    :raises ServiceError: as the route answers it
    """
    view = _view((x0, y0, x1, y1), "viewport", scale, min_px)
    return answers.viewport(doc.snapshot, view, settings.cap(limit), settings.lod_budget)


@router.get(
    "/diff",
    response_class=JSONBytes,
    responses=documented(
        200,
        {
            "version": 4,
            "band": None,
            "reset": False,
            "entered": 1,
            "truncated": False,
            "leave": ["w3"],
            "enter": [ITEM],
        },
        404,
        409,
        422,
    ),
)
async def read_diff(
    doc: DocumentDep,
    settings: SettingsDep,
    registry: RegistryDep,
    from_: Annotated[
        str, Query(alias="from", description="old viewport x0,y0,x1,y1", examples=["0,0,1920,1080"])
    ],
    to: Annotated[str, Query(description="new viewport x0,y0,x1,y1", examples=["0,60,1920,1140"])],
    scale: Scale = None,
    min_px: MinPx = 0.0,
    limit: Limit = None,
    from_scale: Annotated[
        float | None, Query(gt=0, description="the old viewport's scale, when zooming")
    ] = None,
    since: Annotated[
        int | None, Query(ge=0, description="the version the client holds: edited items are carried too")
    ] = None,
    from_band: Annotated[
        int | None,
        Query(
            description="the `band` of the answer the client holds (its aggregates); default: "
            "the band the old viewport would get now"
        ),
    ] = None,
    min_version: MinVersion = None,
) -> Response:
    """Items that entered and ids that left between two viewports; stateless, any replica answers.

    With ``since``, items edited after that version come too: in ``enter`` if shown now, else
    in ``leave``. ``reset: true`` means the edits no longer reach back that far: drop what you
    hold and take ``enter`` as the whole view. ``entered`` counts ``enter`` before ``limit``.
    """
    await registry.catch_up_to(doc, min_version, settings.catch_up_ms / 1000)
    return JSONBytes(
        diff_answer(doc, settings, from_, to, scale, min_px, limit, from_scale, since, from_band)
    )


def diff_answer(
    doc: Document,
    settings: Settings,
    from_: str,
    to: str,
    scale: float | None = None,
    min_px: float = 0.0,
    limit: int | None = None,
    from_scale: float | None = None,
    since: int | None = None,
    from_band: int | None = None,
) -> bytes:
    """The ``/diff`` answer for validated parameters.

    :raises ServiceError: as the route answers it
    """
    old = _view(from_.split(","), "from", from_scale or scale, min_px)
    new = _view(to.split(","), "to", scale, min_px)
    snap: Snapshot = doc.snapshot
    if since is not None and since > snap.version:
        raise Conflict(f"since={since} is newer than the document's version {snap.version}")
    cap = settings.cap(limit)
    if from_band is None:
        old_shown = answers.shown(snap, old, cap, settings.lod_budget)
    elif snap.overview is None or not old.min_size:
        raise Invalid(
            f"from_band={from_band}, but the old viewport has no level of detail (from_scale, min_px)"
        )
    else:
        band = min(max(from_band, snap.overview.lo), snap.overview.hi)
        old_shown = answers.Shown(old.rect, snap.overview.threshold(band), band)
    held = Held(old_shown, snap.version if since is None else since)  # without since: no edits to carry
    return answers.change(snap, new, held, cap, settings.lod_budget).json()


@router.get(
    "/cells",
    tags=["debug"],
    responses=documented(
        200,
        {"version": 4, "cells": [{"depth": 0, "box": [0.0, 0.0, 612.0, 1631208.0], "leaf": False}]},
        404,
        422,
    ),
)
async def read_cells(
    doc: DocumentDep,
    x0: Annotated[float, Query(examples=[0.0])],
    y0: Annotated[float, Query(examples=[0.0])],
    x1: Annotated[float, Query(examples=[1920.0])],
    y1: Annotated[float, Query(examples=[1080.0])],
    limit: Annotated[int, Query(ge=1, le=20_000, description="most cells to return")] = 2000,
) -> dict:
    """The index's nodes touching the viewport, shallowest first: each the union box of its
    items, with its depth and whether it is a leaf. For seeing the structure, not for panning."""
    view = _view((x0, y0, x1, y1), "viewport")
    snap: Snapshot = doc.snapshot
    cells = snap.tree.cells(view.rect, limit=limit)
    return {
        "version": snap.version,
        "cells": [{"depth": d, "box": box, "leaf": leaf} for d, box, leaf in cells],
    }


# -- the fast path ---------------------------------------------------------------------------

# Query values the fast path converts itself: forms pydantic parses to the same number as
# float() and int() do. Anything else (blank, "nan", "1_0", a duplicate...) goes to FastAPI.
_FLOAT = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d{1,4})?")
_INT = re.compile(r"[-+]?\d{1,18}")


_PLAIN = "0123456789.+-"  # a decimal without exponent: float() takes exactly what _FLOAT does


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


def _above_0(text: str) -> float:
    value = _float(text)
    if not value > 0:  # Query(gt=0)
        raise _Slow
    return value


def _at_least_0(text: str) -> float:
    value = _float(text)
    if not value >= 0:  # Query(ge=0)
        raise _Slow
    return value


def _int_at_least(lowest: int) -> Callable[[str], int]:
    def convert(text: str) -> int:
        value = _int(text)
        if value < lowest:  # Query(ge=lowest)
            raise _Slow
        return value

    return convert


class _Slow(Exception):
    """This request is for the full route: FastAPI validates it and words the 422."""


# Per route: its answer function, its required query names and its converters, by query name
# (keyword argument name: from -> from_). Kept next to the routes' declarations above; the
# tests compare the two paths on every parameter.
_ROUTES: dict[str, tuple[Callable[..., bytes], frozenset[str], dict[str, tuple[str, Callable[[str], Any]]]]]
_ROUTES = {
    "viewport": (
        viewport_answer,
        frozenset({"x0", "y0", "x1", "y1"}),
        {
            "x0": ("x0", _float),
            "y0": ("y0", _float),
            "x1": ("x1", _float),
            "y1": ("y1", _float),
            "scale": ("scale", _above_0),
            "min_px": ("min_px", _at_least_0),
            "limit": ("limit", _int_at_least(1)),
            "min_version": ("min_version", _int_at_least(0)),
        },
    ),
    "diff": (
        diff_answer,
        frozenset({"from", "to"}),
        {
            "from": ("from_", str),
            "to": ("to", str),
            "scale": ("scale", _above_0),
            "min_px": ("min_px", _at_least_0),
            "limit": ("limit", _int_at_least(1)),
            "from_scale": ("from_scale", _above_0),
            "since": ("since", _int_at_least(0)),
            "from_band": ("from_band", _int),
            "min_version": ("min_version", _int_at_least(0)),
        },
    ),
}
_JSON = b"application/json"


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


def _arguments(route: str, raw: bytes) -> tuple[Callable[..., bytes], dict[str, Any]]:
    """The answer function and its keyword arguments, as FastAPI would validate them.

    :raises _Slow: unless every parameter is present once and plainly valid
    """
    answer, required, converters = _ROUTES[route]
    kwargs: dict[str, Any] = {}
    seen = set()
    for name, value in _query(raw):
        if name in seen:
            raise _Slow  # FastAPI takes the last; not worth copying
        seen.add(name)
        converter = converters.get(name)
        if converter is not None:
            kwargs[converter[0]] = converter[1](value)
    if not required <= seen:
        raise _Slow
    return answer, kwargs


class HotRoutes:
    """``GET /documents/{doc}/viewport`` and ``/diff`` without the framework's per-request work.

    A pan sends one of these per frame, and the answer itself (an index diff and a join of
    pre-encoded JSON) took a fraction of what routing, dependency solving, pydantic validation
    and five middlewares took around it. Wrapped around the whole stack (``main``), it
    answers a plainly valid request the way the full stack would, with the same pieces: the
    guard's own admission check, the same answer functions the routes call, the document
    handled as ``deps._document`` handles it (caught up with the store, pinned while the answer
    is built and sent), and gzip as ``GZipMiddleware`` does it. Anything else (another route or
    method, a missing, repeated or odd parameter, a value out of range, a refused request, a
    browser origin when CORS is on, any error while answering) goes on to the full stack,
    which answers it as it always did: every validation message and error comes from there.
    """

    def __init__(
        self,
        app: ASGIApp,
        state: Any,
        admit: Callable[[Scope], None],
        gzip_min_bytes: int | None,
        cors: bool,
    ) -> None:
        self.app, self.state, self.admit, self.gzip_min_bytes, self.cors = (
            app,
            state,
            admit,
            gzip_min_bytes,
            cors,
        )

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
        doc_id, _, route = path[11:].partition("/")
        if not doc_id or route not in _ROUTES:
            return False
        encoding = None
        for name, value in scope["headers"]:
            if name == b"accept-encoding":
                if encoding is None:  # the first, as Starlette's Headers.get reads it
                    encoding = value
            elif name == b"origin" and self.cors:
                return False  # CORSMiddleware adds its headers
        try:
            answer, kwargs = _arguments(route, scope["query_string"])
            self.admit(scope)
        except Exception:  # _Slow, or the guard's refusal: the full stack words it
            return False
        registry: Registry = self.state.registry
        try:
            doc = await registry.get(doc_id)
        except Exception:  # a 404, or the store failing: the full stack answers it
            return False
        if kwargs.pop("min_version", 0) > doc.snapshot.version:
            return False  # the route waits for it
        with registry.pinned(doc):
            try:
                body = answer(doc, self.state.settings, **kwargs)
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
            else:

                async def respond(scope: Scope, receive: Receive, send: Send) -> None:
                    await send(start)
                    await send(message)

                await GZipResponder(respond, minimum, compresslevel=GZIP_LEVEL)(scope, receive, send)
        return True
