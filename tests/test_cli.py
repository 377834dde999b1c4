"""The `vantage` command: help, demo documents, and a real server process answering on loopback."""

import os
import socket
import subprocess
import sys
import time
from contextlib import contextmanager

import httpx
import numpy as np

import oracle
from app.demo import DEMOS


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_help_lists_the_commands():
    result = subprocess.run([sys.executable, "-m", "app.cli", "--help"], capture_output=True, text=True, check=True)
    assert "serve" in result.stdout


@contextmanager
def serving(data_dir):
    """A `vantage serve` process on a free loopback port; yields its base URL once it answers."""
    port = free_port()
    env = {**os.environ, "VANTAGE_DATA_DIR": str(data_dir)}
    server = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "serve", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                httpx.get(f"{url}/health", timeout=1)
                break
            except httpx.TransportError:
                assert server.poll() is None, server.stdout.read()
                assert time.monotonic() < deadline, "server did not come up in 60 s"
                time.sleep(0.1)
        yield url
    finally:
        server.terminate()
        server.communicate(timeout=10)  # reaps it and closes its pipe


def test_serve_starts_a_server_that_answers_health(tmp_path):
    with serving(tmp_path) as url:
        response = httpx.get(f"{url}/health")
        assert response.status_code == 200
        assert response.json() == {"status": "ok"}


def test_demo_creates_documents_worth_panning_that_the_server_serves(tmp_path):
    made = subprocess.run([sys.executable, "-m", "app.cli", "demo", "--data-dir", str(tmp_path)],
                          capture_output=True, text=True, check=True)  # fmt: skip
    assert "created" in made.stdout
    again = subprocess.run([sys.executable, "-m", "app.cli", "demo", "--data-dir", str(tmp_path)],
                           capture_output=True, text=True, check=True)  # fmt: skip
    assert "already present" in again.stdout
    with serving(tmp_path) as url:
        documents = {d["name"]: d for d in httpx.get(f"{url}/documents").json()}
        assert set(documents) == set(DEMOS) and sum(d["items"] for d in documents.values()) >= 1_000_000
        for name, make in DEMOS.items():
            boxes, _ = make()
            assert documents[name]["items"] == len(boxes)
            x0, y0 = boxes[len(boxes) // 2, :2]
            rect = (x0, y0, x0 + 1920, y0 + 1080)
            params = {**dict(zip(("x0", "y0", "x1", "y1"), rect)), "limit": 100_000}
            body = httpx.get(f"{url}/documents/{documents[name]['id']}/viewport", params=params).json()
            shown = np.array([[item[k] for k in ("x0", "y0", "x1", "y1")] for item in body["items"]])
            assert len(body["items"]) == body["count"] == oracle.hits(boxes, rect).sum() > 10
            assert sorted(map(tuple, shown.tolist())) == sorted(map(tuple, boxes[oracle.hits(boxes, rect)].tolist()))
