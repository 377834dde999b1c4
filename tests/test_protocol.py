"""The HTTP protocol `vantage serve` runs (app/protocol.py), in a real server process: a
response's head and body leave in one socket write, and holding a write back loses nothing
and reorders nothing (a head with no body after it, pipelined requests, a streamed export)."""

import asyncio
import http.client
import socket
from urllib.parse import urlsplit

import h11
import httpx
import pytest
from service import NDJSON, ndjson

from app.launch import launch, stop
from app.protocol import _Cork
from spatial import scenes

REQUESTS = 200


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """``(process, url, doc id, item count)``: a server holding a two-page document."""
    boxes, kinds = scenes.long_document(pages=2, seed=3)
    process, url = launch(tmp_path_factory.mktemp("protocol-data"))
    try:
        with httpx.Client(base_url=url) as c:
            doc = c.post("/documents", json={"name": "protocol"}).json()["id"]
            c.post(f"/documents/{doc}/items", content=ndjson(boxes, kinds), headers=NDJSON).raise_for_status()
        yield process, url, doc, len(boxes)
    finally:
        stop(process, timeout=15)
        process.communicate()


def _writes(pid: int) -> int:
    """The process's write system calls so far (``write``, ``writev``: what its sockets use)."""
    with open(f"/proc/{pid}/io") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("syscw:"))


def _connection(url: str, timeout: float = 10) -> http.client.HTTPConnection:
    parts = urlsplit(url)
    return http.client.HTTPConnection(parts.hostname, parts.port, timeout=timeout)


def test_a_response_leaves_in_one_socket_write(served):
    process, url, doc, _ = served
    path = f"/documents/{doc}/viewport?x0=0&y0=0&x1=800&y1=600"
    connection = _connection(url)  # one kept-alive connection: no accept or close to count
    connection.request("GET", path)
    expected = connection.getresponse().read()
    before = _writes(process.pid)
    for _ in range(REQUESTS):
        connection.request("GET", path)
        response = connection.getresponse()
        assert response.status == 200
        assert response.read() == expected
    writes = _writes(process.pid) - before
    connection.close()
    assert len(expected) > 1000
    # uvicorn's own protocol makes two a response (the head, then the body)
    assert writes <= REQUESTS * 1.1, f"{writes} writes for {REQUESTS} responses"


def test_a_head_with_no_body_after_it_is_sent(served):
    _, url, _, _ = served
    # Times out if the head were held for a body never sent: within the 5 s after which
    # uvicorn closes an idle connection, which would send it.
    connection = _connection(url, timeout=2)
    connection.request("HEAD", "/static/favicon.svg")
    response = connection.getresponse()
    assert response.status == 200
    assert int(response.headers["content-length"]) > 0
    assert response.read() == b""
    connection.close()


def test_pipelined_requests_are_answered_whole_and_in_order(served):
    _, url, doc, _ = served
    parts = urlsplit(url)
    paths = [
        "/health",
        f"/documents/{doc}/viewport?x0=0&y0=0&x1=800&y1=600",
        "/static/favicon.svg",
        f"/documents/{doc}/diff?from=0,0,800,600&to=0,50,800,650",
        "/documents/nothing-here/viewport?x0=0&y0=0&x1=1&y1=1",
    ]
    expected = []
    with httpx.Client(base_url=url) as c:
        for path in paths:
            answer = c.get(path)
            expected.append((answer.status_code, answer.content))
    wire = b"".join(f"GET {path} HTTP/1.1\r\nHost: {parts.netloc}\r\n\r\n".encode() for path in paths)
    client = h11.Connection(h11.CLIENT)  # reads the answers; told of each request as it is due

    def expect(path: str) -> None:
        client.send(h11.Request(method="GET", target=path, headers=[("Host", parts.netloc)]))
        client.send(h11.EndOfMessage())

    got = []
    with socket.create_connection((parts.hostname, parts.port), timeout=10) as sock:
        sock.sendall(wire)  # all at once: each answer is written while the next request waits
        expect(paths[0])
        status, body = None, b""
        while len(got) < len(paths):
            event = client.next_event()
            if event is h11.NEED_DATA:
                client.receive_data(sock.recv(65536))
            elif isinstance(event, h11.Response):
                status, body = event.status_code, b""
            elif isinstance(event, h11.Data):
                body += event.data
            elif isinstance(event, h11.EndOfMessage):
                got.append((status, body))
                if len(got) < len(paths):
                    client.start_next_cycle()
                    expect(paths[len(got)])
    assert got == expected


def test_a_streamed_export_arrives_whole(served):
    _, url, doc, n = served
    with httpx.Client(base_url=url) as c, c.stream("GET", f"/documents/{doc}/items") as answer:
        assert answer.status_code == 200
        lines = [line for line in answer.iter_lines() if line]
    assert len(lines) == n


def test_a_malformed_request_gets_its_400_before_the_connection_closes(served):
    """uvicorn answers a request it cannot parse and closes: the held answer leaves with the close."""
    _, url, _, _ = served
    parts = urlsplit(url)
    with socket.create_connection((parts.hostname, parts.port), timeout=10) as sock:
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\nBad Header Line\r\n\r\n")
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 400 "), answer[:200]


class _Transport:
    """What the cork writes to: the writes it received, in order."""

    def __init__(self) -> None:
        self.written: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.written.append(bytes(data))

    def writelines(self, chunks) -> None:
        self.written.append(b"".join(chunks))

    def is_closing(self) -> bool:
        return False

    def close(self) -> None:
        self.written.append(b"<closed>")


def test_a_held_write_leaves_at_the_loop_s_next_turn_or_at_close():
    async def main() -> list[list[bytes]]:
        raw = _Transport()
        cork = _Cork(raw, asyncio.get_running_loop())
        cork.write(b"head")
        seen = [list(raw.written)]  # held
        await asyncio.sleep(0)  # one turn of the loop
        seen.append(list(raw.written))
        cork.write(b"head2")
        cork.write(b"body")  # joins it
        seen.append(list(raw.written))
        cork.write(b"last")
        cork.close()  # never held back past the close
        seen.append(list(raw.written))
        return seen

    held, turned, joined, closed = asyncio.run(main())
    assert held == [] and turned == [b"head"]
    assert joined == [b"head", b"head2body"]
    assert closed == [b"head", b"head2body", b"last", b"<closed>"]
