"""A Python client of a Vantage server (httpx, sync and async) and its pan stream.

One method a route, the same on :class:`Client` and :class:`AsyncClient` (whose methods are
coroutines, typed as such: ``await client.health()`` is a ``dict``); a non-2xx answer raises
:class:`VantageError`, carrying the status and the server's ``detail``::

    with Client("http://127.0.0.1:8000", token="s3cret") as vantage:
        doc = vantage.create_document("report")["id"]
        vantage.import_items(doc, Path("report.ndjson.gz"))  # streamed from disk
        vantage.import_items(doc, ({"id": f"n{i}", "x0": i, "y0": 0, "x1": i + 1, "y1": 1} for i in range(10)))
        vantage.viewport(doc, (0, 0, 1920, 1080), scale=0.5, min_px=1)
        with vantage.stream(doc, scale=0.5, min_px=1) as stream:
            stream.view((0, 0, 1920, 1080))  # what entered and left; stream.items holds the view
            stream.view((0, 500, 1920, 1580))

The simulator, the benchmarks and the tests talk to servers through this package (and start
them with :mod:`app.launch`) rather than each on its own. Its stream needs websockets, which
uvicorn's ``standard`` extra installs. Import from here; the parts are

- :mod:`app.client.clients`: :class:`Client` and :class:`AsyncClient`, one method a route;
- :mod:`app.client.uploads`: what an import sends (a body streamed from a path, bytes, a file
  or items), and the upload of parts a big one goes as;
- :mod:`app.client.streams`: :class:`Stream` and :class:`AsyncStream`, the WebSocket pan stream;

and this module holds what they share: the error, how a request is written and its answer
read, and the bearer token (renewed ``RENEW_SECONDS`` before it expires: set it here).
"""

from __future__ import annotations

import base64
import json
import time
from collections.abc import Callable, Generator, Iterable
from typing import Any
from urllib.parse import quote

import httpx

__all__ = [
    "AsyncClient",
    "AsyncStream",
    "Client",
    "Stream",
    "VantageError",
]

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


# -- the token, for both clients and both streams ---------------------------------------------------

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


# -- the parts, last: each imports what it shares from above -------------------------------------
# (their settings too, importable from here as before: each is read in the module defining it)

from app.client.clients import AsyncClient, Client  # noqa: E402
from app.client.streams import CLOSES as CLOSES  # noqa: E402
from app.client.streams import GRACE as GRACE  # noqa: E402
from app.client.streams import AsyncStream, Stream  # noqa: E402
from app.client.uploads import CHUNK as CHUNK  # noqa: E402
from app.client.uploads import NDJSON as NDJSON  # noqa: E402
from app.client.uploads import PART_BYTES as PART_BYTES  # noqa: E402
from app.client.uploads import PART_TRIES as PART_TRIES  # noqa: E402
