"""The door every request passes before a route sees it, and before any body byte is read.

In order: the ``Host`` header names this server (no DNS rebinding); the path is valid UTF-8
once %-decoded; writes (any method but GET, HEAD and OPTIONS) and the stream come from no
browser origin or an allowed one; the token, when one is needed (writes always; reads of
documents with ``VANTAGE_READ_TOKEN`` or a JWT key, and then ``/stats`` and the API docs with
``VANTAGE_READ_TOKEN``; ``?token=`` only for reads and the stream, which a browser cannot give
headers), and that it grants what is asked: the document named in the path, to read or to
write, or creating one; then the body is capped in size and time as it is read, so an
oversized or trickled body is cut off at the limit, never read whole first.

The request's grant is left in ``scope["state"]["grant"]`` for the routes that filter by it.
"""

import asyncio
import functools
import logging
import re
from collections.abc import Mapping
from urllib.parse import unquote_to_bytes, urlsplit

import orjson
from starlette.datastructures import Headers, QueryParams
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .access import Access, Grant
from .config import Settings
from .errors import BadRequest, Forbidden, ServiceError, SlowBody, TooMany

__all__ = ["Guard"]

SAFE = frozenset({"GET", "HEAD", "OPTIONS"})
# The routes whose body is a bulk import, or a part of one
IMPORT = re.compile(r"^/documents/[^/]+/(?:items/?|uploads/[^/]+/parts/[^/]+)$")
OPERATOR = frozenset({"/stats", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json"})
log = logging.getLogger("vantage.access")


class Guard:
    def __init__(self, app: ASGIApp, settings: Settings, access: Access) -> None:
        self.app, self.settings, self.access = app, settings, access
        self.hosts = settings.hosts
        self.origins = set(settings.origins)
        self.documents_need_token = settings.read_token or access.signed

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        try:
            self.admit(scope)
        except ServiceError as error:
            refuse = _refuse_http if kind == "http" else _refuse_websocket
            return await refuse(error.status, error.message, error.headers or {}, receive, send)
        if kind == "http" and scope["method"] not in SAFE:
            receive = self._capped(scope, receive)
        await self.app(scope, receive, send)

    def admit(self, scope: Scope) -> None:
        """:raises ServiceError: the first reason to refuse the request"""
        host = origin = authorization = None
        for name, value in scope["headers"]:  # the first of each, as Headers.get reads them
            if name == b"host":
                host = value.decode("latin-1") if host is None else host
            elif name == b"origin":
                origin = value.decode("latin-1") if origin is None else origin
            elif name == b"authorization":
                authorization = value if authorization is None else authorization
        host = host or ""
        path = scope["path"]
        # /health says only whether the server is up: load balancers' and orchestrators' probes
        # name it by whatever address they know, and a rebound page learns nothing from it.
        if self.hosts is not None and _hostname(host) not in self.hosts and path != "/health":
            raise BadRequest(
                f"the Host header {host!r} is not a name this server answers to (VANTAGE_ALLOWED_HOSTS)"
            )
        try:
            unquote_to_bytes(scope.get("raw_path") or path.encode()).decode()
        except UnicodeDecodeError:
            raise BadRequest("the URL path is not UTF-8 once %-decoded") from None
        write = scope["type"] == "http" and scope["method"] not in SAFE
        foreign = origin is not None and origin not in self.origins and urlsplit(origin).netloc != host
        if (write or scope["type"] == "websocket") and foreign:
            raise Forbidden(
                f"requests from the origin {origin!r} are not allowed here (VANTAGE_CORS_ORIGINS)"
            )
        document = path.startswith("/documents")
        if not (
            write
            or (document and self.documents_need_token)
            or (path in OPERATOR and self.settings.read_token)
        ):
            return
        # A header's bytes as sent (a token may hold any UTF-8); the query's %-decoded as UTF-8.
        scheme, _, given = (authorization or b"").partition(b" ")
        if scheme.lower() != b"bearer":
            given = b"" if write else QueryParams(scope["query_string"]).get("token", "").encode()
        grant = self.access.grant(given)
        if document:
            _check_grant(grant, path, write)
        scope.setdefault("state", {})["grant"] = grant
        if write and grant.subject is not None:
            log.info("%s %s by %s", scope["method"], path, grant.subject)

    def _capped(self, scope: Scope, receive: Receive) -> Receive:
        """``receive`` refusing a body past its limit (413) or slower than the timeout (408)."""
        if IMPORT.match(scope["path"]):
            limit, setting = self.settings.max_body_bytes, "VANTAGE_MAX_BODY_BYTES"
        else:
            limit, setting = self.settings.max_json_bytes, "VANTAGE_MAX_JSON_BYTES"
        declared = Headers(scope=scope).get("content-length")
        too_large = TooMany(f"the body exceeds {limit} bytes, the most this route takes ({setting})")
        timeout = self.settings.body_timeout
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        size = 0

        async def receive_capped() -> Message:
            nonlocal size
            if declared is not None and declared.isdigit() and int(declared) > limit:
                raise too_large  # before reading a byte
            try:
                async with asyncio.timeout_at(deadline):
                    message = await receive()
            except TimeoutError:
                raise SlowBody(
                    f"the body took longer than {timeout:g} s to arrive (VANTAGE_BODY_TIMEOUT)"
                ) from None
            size += len(message.get("body", b""))
            if size > limit:
                raise too_large
            return message

        return receive_capped


def _check_grant(grant: Grant, path: str, write: bool) -> None:
    """:raises Forbidden: unless ``grant`` allows this request on the document in ``path``"""
    doc = path[len("/documents/") :].partition("/")[0] if path.startswith("/documents/") else ""
    if not doc:  # the list (filtered by the grant), or creating a document
        if write and not grant.create:
            raise Forbidden("the token does not allow creating documents (its claim `create` is not true)")
    elif write and not grant.writes(doc):
        raise Forbidden(
            f"the token does not allow writing document {doc!r} (it needs 'write' for it in `docs`)"
        )
    elif not grant.reads(doc):
        raise Forbidden(f"the token does not allow reading document {doc!r} (it is not in its `docs`)")


@functools.lru_cache(maxsize=256)  # a few names, parsed once each (and at most 256 kept)
def _hostname(host: str) -> str:
    """``host`` without its port, lower case (``[::1]:8000`` -> ``::1``)."""
    name = urlsplit(f"//{host}").hostname
    return name or ""


async def _refuse_http(
    status: int, message: str, headers: Mapping[str, str], receive: Receive, send: Send
) -> None:
    body = orjson.dumps({"detail": message})
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    raw += [(k.lower().encode(), v.encode()) for k, v in headers.items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})


async def _refuse_websocket(
    status: int, message: str, headers: Mapping[str, str], receive: Receive, send: Send
) -> None:
    """Accept, say why in an error message, then close with 4000 + the HTTP status: a browser
    sees neither the status nor the body of a refused handshake."""
    if (await receive())["type"] != "websocket.connect":
        return
    await send({"type": "websocket.accept"})
    await send(
        {"type": "websocket.send", "text": orjson.dumps({"type": "error", "message": message}).decode()}
    )
    await send({"type": "websocket.close", "code": 4000 + status, "reason": message[:120]})
