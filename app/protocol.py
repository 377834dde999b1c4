"""The HTTP/1.1 protocol Vantage serves with: uvicorn's httptools protocol, with a response's
head and body leaving in one socket write.

uvicorn writes a response's status line and headers when the app sends
``http.response.start`` and the body when it sends ``http.response.body``: two ``send``
calls, two TCP segments, and on loopback the receiving side's work is done in the sender's
system call too. One write instead took ~7 µs of system CPU off a viewport request (~80 µs
in all) and ~8 µs off a diff; a bare app went from 35 to 24 µs of CPU per 108 kB response and
from 21 to 17 µs per small one. Here a small write is held until the next write joins it or
the event loop turns over, whichever comes first, so a head and the body sent after it go as
one ``writelines``.
Nothing is reordered and nothing waits longer than one turn of the loop.

Use it with ``uvicorn --http app.protocol:CorkedHttp`` (``vantage serve`` does).
"""

import asyncio
from typing import Any, cast

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

__all__ = ["CorkedHttp", "DrainedWebSocket", "HOLD_BYTES", "UVICORN_HTTP", "UVICORN_WS"]

#: uvicorn's ``http`` setting (``--http``) for this protocol.
UVICORN_HTTP = "app.protocol:CorkedHttp"
#: uvicorn's ``ws`` setting (``--ws``) for the WebSocket protocol below.
UVICORN_WS = "app.protocol:DrainedWebSocket"

#: Writes smaller than this wait (one loop turn at most) for the write after them.
HOLD_BYTES = 16 * 1024


class _Cork:
    """A transport whose small writes wait for the next one; everything else passes through."""

    __slots__ = ("_flush_soon", "_held", "_loop", "raw")

    def __init__(self, raw: asyncio.Transport, loop: asyncio.AbstractEventLoop) -> None:
        self.raw, self._loop = raw, loop
        self._held: bytes | None = None
        self._flush_soon: asyncio.Handle | None = None

    def write(self, data: bytes) -> None:
        held = self._held
        if held is not None:
            self._held = None
            self._flush_soon.cancel()  # type: ignore[union-attr]  # set whenever _held is
            self.raw.writelines((held, data))
        elif len(data) < HOLD_BYTES:
            self._held = bytes(data)  # the caller may reuse its buffer
            self._flush_soon = self._loop.call_soon(self.flush)
        else:
            self.raw.write(data)

    def writelines(self, chunks: Any) -> None:
        self.flush()
        self.raw.writelines(chunks)

    def flush(self) -> None:
        held, self._held = self._held, None
        if held is not None and not self.raw.is_closing():
            self.raw.write(held)

    def write_eof(self) -> None:
        self.flush()
        self.raw.write_eof()

    def close(self) -> None:
        self.flush()
        self.raw.close()

    def abort(self) -> None:
        self._held = None
        self.raw.abort()

    def is_closing(self) -> bool:  # asked after every response: not through __getattr__
        return self.raw.is_closing()

    def __getattr__(self, name: str) -> Any:  # get_extra_info, pause_reading, ...
        return getattr(self.raw, name)


class CorkedHttp(HttpToolsProtocol):
    """uvicorn's httptools protocol writing through :class:`_Cork`."""

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]  # as uvicorn's
        # a _Cork passes for the Transport it wraps (__getattr__ forwards the rest)
        super().connection_made(cast(asyncio.Transport, _Cork(transport, asyncio.get_running_loop())))

    def handle_websocket_upgrade(self) -> None:
        # A WebSocket protocol takes the connection over: it gets the plain transport, and
        # its messages are written as it sends them.
        cork = cast(_Cork, self.transport)  # connection_made gave it one
        cork.flush()
        self.transport = cork.raw
        super().handle_websocket_upgrade()


class DrainedWebSocket(WebSocketsSansIOProtocol):
    """uvicorn's WebSocket protocol whose ``send`` of a message returns once the message has
    left for the client (the transport's buffer drained below its low-water mark), not as soon
    as it is queued in that buffer. A client that stops reading then holds its sender at the
    send, where the stream's timeout and the server's budget of unread bytes can see it,
    instead of leaving each message's bytes in memory unseen."""

    async def send(self, message: Any) -> None:
        await super().send(message)
        if message["type"] == "websocket.send":
            await self.writable.wait()  # set again when the buffer drains, or the connection is lost
