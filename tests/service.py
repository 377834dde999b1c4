"""Helpers for tests of the service: a client, a real server process, NDJSON bodies, and the
brute-force answers."""

import os
import re
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import anyio
import numpy as np
import oracle
import orjson
from fastapi.testclient import TestClient

from app.demo import ndjson_lines
from app.launch import launch, stop

ROOT = Path(__file__).resolve().parent.parent

NDJSON = {"content-type": "application/x-ndjson"}  # an import's body type


def client() -> TestClient:
    """A TestClient of an app made for the settings the environment holds now."""
    from app.config import LOOPBACK_NAMES, get_settings
    from app.main import create_app

    get_settings.cache_clear()
    settings = get_settings()
    if not os.environ.get("VANTAGE_ALLOWED_HOSTS"):  # TestClient's WebSockets say `Host: testserver`
        settings = settings.model_copy(update={"allowed_hosts": ",".join([*LOOPBACK_NAMES, "testserver"])})
    return TestClient(create_app(settings), base_url="http://127.0.0.1")


def receive(ws, timeout: float = 10.0) -> dict:
    """The next message of a TestClient WebSocket as JSON; AssertionError after ``timeout``
    seconds, so a missing message fails in seconds instead of hanging the suite.

    :raises WebSocketDisconnect: if the server closed the stream instead
    """

    async def next_message() -> dict:
        with anyio.fail_after(timeout):
            return await ws._send_rx.receive()  # what TestClient's own receive awaits, without a bound

    try:
        message = ws.portal.call(next_message)
    except TimeoutError:
        raise AssertionError(f"no message from the stream within {timeout:g} s") from None
    ws._raise_on_close(message)
    return orjson.loads(message["text"])


def ndjson(boxes: np.ndarray, kinds=None) -> bytes:
    return b"".join(ndjson_lines(boxes, kinds))


def item_json(item_id: str, box, **fields) -> bytes:
    """An item's JSON as an import stores it, its box in it (a float's text reads back exactly)."""
    return orjson.dumps(
        {"id": item_id, **dict(zip(("x0", "y0", "x1", "y1"), map(float, box), strict=True)), **fields}
    )


def ids_of(items) -> set[str]:
    return {item["id"] for item in items}


def expected(boxes: np.ndarray, rect, min_size: float = 0.0) -> set[str]:
    return {f"i{i}" for i in np.flatnonzero(oracle.hits(boxes, rect, min_size))}


def spawn_server(
    data_dir: Path, *args: str, env: dict[str, str] | None = None
) -> tuple[subprocess.Popen, str]:
    """A `vantage serve` process on a free loopback port, once it answers: ``(process, url)``
    (``env``: settings of its own)."""
    return launch(data_dir, *args, env=env)


@contextmanager
def serving(data_dir: Path) -> Iterator[str]:
    """A `vantage serve` process on a free loopback port; yields its base URL once it answers."""
    server, url = spawn_server(data_dir)
    try:
        yield url
    finally:
        server.terminate()
        try:
            server.communicate(timeout=10)  # reaps it and closes its pipe
        except subprocess.TimeoutExpired:  # still running: killed, so it never outlives the test
            server.kill()
            server.communicate()


class Output:
    """What a server process prints, read by a thread as it comes (a full pipe would stall it).
    Use it instead of ``communicate``."""

    def __init__(self, process: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self._process = process
        self._changed = threading.Condition()
        self._reader = threading.Thread(target=self._read, args=(process,), daemon=True)
        self._reader.start()

    def stop(self) -> None:
        """Stop the server (SIGTERM, then SIGKILL after 15 s) and read the rest of its output."""
        stop(self._process, timeout=15)
        self._reader.join(timeout=10)
        self._process.stdout.close()

    def _read(self, process: subprocess.Popen) -> None:
        for line in process.stdout:
            with self._changed:
                self.lines.append(line)
                self._changed.notify_all()

    def wait_for(self, text: str, timeout: float = 60, times: int = 1) -> None:
        """Until ``times`` lines holding ``text`` are printed; AssertionError after ``timeout``
        seconds."""
        with self._changed:
            if not self._changed.wait_for(lambda: sum(text in line for line in self.lines) >= times, timeout):
                raise AssertionError(f"the server never printed {text!r} {times} times; it printed:\n{self}")

    def __str__(self) -> str:
        return "".join(self.lines)


def raw_http(url: str, request: bytes, timeout: float = 10) -> tuple[int, dict]:
    """Send ``request`` as bytes on a new connection and read the answer, ``(status, JSON
    body)``: for bodies that never finish, which no HTTP client sends."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=timeout) as connection:
        connection.sendall(request)
        answer = b""
        while True:
            head, _, body = answer.partition(b"\r\n\r\n")
            length = re.search(rb"(?i)content-length: *(\d+)", head)
            if length and len(body) >= int(length.group(1)):
                return int(head.split()[1]), orjson.loads(body)
            chunk = connection.recv(65536)
            if not chunk:
                raise AssertionError(f"the connection closed before a whole answer: {answer!r}")
            answer += chunk


def in_fresh_interpreter(script: str, *args: str, timeout: float) -> object:
    """Run ``script`` in a new Python process from the repository root (for what a process
    does once: compiling, setting a global provider) and decode the JSON it prints last."""
    done = subprocess.run(
        [sys.executable, "-c", script, *args], capture_output=True, text=True, cwd=ROOT, timeout=timeout
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return orjson.loads(done.stdout.strip().splitlines()[-1])


def mapped_bytes(path: Path) -> int:
    """Bytes of the pages of ``path`` (a file, or the files in a directory) mapped into this
    process now: the ``Rss`` of their mappings."""
    resident, ours = 0, False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        if "-" in line.split(" ", 1)[0]:  # a mapping's first line: its range, ..., its path
            ours = line.endswith(f" {path}") or f" {path}/" in line
        elif ours and line.startswith("Rss:"):
            resident += int(line.split()[1]) << 10
    return resident
