"""Helpers for tests of the service: a client, a real server process, NDJSON bodies, and the
brute-force answers."""

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
from fastapi.testclient import TestClient

import oracle
from app.demo import ndjson_lines


def client() -> TestClient:
    from app.main import app

    return TestClient(app)


def ndjson(boxes: np.ndarray, kinds=None) -> bytes:
    return b"".join(ndjson_lines(boxes, kinds))


def ids_of(items) -> set[str]:
    return {item["id"] for item in items}


def expected(boxes: np.ndarray, rect, min_size: float = 0.0) -> set[str]:
    return {f"i{i}" for i in np.flatnonzero(oracle.hits(boxes, rect, min_size))}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def spawn_server(data_dir: Path, *args: str) -> tuple[subprocess.Popen, str]:
    """A `vantage serve` process on a free loopback port, once it answers: ``(process, url)``."""
    port = free_port()
    env = {**os.environ, "VANTAGE_DATA_DIR": str(data_dir)}
    server = subprocess.Popen([sys.executable, "-m", "app.cli", "serve", "--port", str(port), *args],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while True:
        try:
            httpx.get(f"{url}/health", timeout=1)
            return server, url
        except httpx.TransportError:
            if server.poll() is not None or time.monotonic() > deadline:
                server.kill()
                raise AssertionError(f"the server did not come up: {server.communicate()[0]}") from None
            time.sleep(0.1)


@contextmanager
def serving(data_dir: Path) -> Iterator[str]:
    """A `vantage serve` process on a free loopback port; yields its base URL once it answers."""
    server, url = spawn_server(data_dir)
    try:
        yield url
    finally:
        server.terminate()
        server.communicate(timeout=10)  # reaps it and closes its pipe
