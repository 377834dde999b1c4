"""`vantage serve --workers 2`, real processes: connections and streams opened in a burst land on
both workers in every round, a killed worker is replaced on its socket while the other serves,
and a port already taken is refused rather than shared."""

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import httpx
import orjson
import pytest
from service import Output
from websockets.sync.client import connect

from app.launch import launch
from app.workers import reuse_port_available

pytestmark = pytest.mark.skipif(not reuse_port_available(), reason="SO_REUSEPORT balances only on Linux")

ROUNDS, BURST = 5, 16


@pytest.fixture(scope="module")
def two_workers(tmp_path_factory):
    """`vantage serve --workers 2`: ``(url, output)``."""
    server, url = launch(tmp_path_factory.mktemp("data"), "--workers", "2", "--log-level", "info")
    output = Output(server)
    try:
        doc = httpx.post(f"{url}/documents", json={"name": "spread"}).json()["id"]
        yield url, doc, output
    finally:
        output.stop()


def _burst_of_connections(url: str) -> list[int]:
    """BURST connections opened at once (all connected before any request is sent, as a load
    balancer's pool opens them), then one ``/stats`` on each: the worker that accepted each."""
    host, port = url.removeprefix("http://").split(":")
    sockets = [socket.create_connection((host, int(port)), timeout=10) for _ in range(BURST)]
    try:
        for sock in sockets:
            sock.sendall(b"GET /stats HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        return [_json_body(sock)["worker"] for sock in sockets]
    finally:
        for sock in sockets:
            sock.close()


def _json_body(sock: socket.socket) -> dict:
    answer = b""
    while b"\r\n\r\n" not in answer or not answer.rstrip().endswith(b"}"):
        chunk = sock.recv(65536)
        assert chunk, f"the connection closed before a whole answer: {answer!r}"
        answer += chunk
    return orjson.loads(answer.partition(b"\r\n\r\n")[2])


def test_connections_opened_at_once_land_on_both_workers_in_every_round(two_workers):
    url, _, _ = two_workers
    for round_ in range(ROUNDS):
        workers = _burst_of_connections(url)
        assert len(set(workers)) == 2, f"round {round_}: every connection went to worker {workers[0]}"


def test_streams_opened_at_once_land_on_both_workers_in_every_round(two_workers):
    url, doc, _ = two_workers
    for round_ in range(ROUNDS):
        start, workers = threading.Barrier(BURST), []

        def stream() -> None:
            start.wait(timeout=10)
            with connect(f"{url.replace('http', 'ws')}/documents/{doc}/stream", open_timeout=10) as ws:
                ws.send(orjson.dumps({"seq": 0, "viewport": [0, 0, 100, 100]}).decode())
                assert orjson.loads(ws.recv(timeout=10))["type"] == "view"
                workers.append(ws.response.headers["x-vantage-worker"])

        threads = [threading.Thread(target=stream) for _ in range(BURST)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=30)
        assert len(workers) == BURST
        assert len(set(workers)) == 2, f"round {round_}: every stream went to worker {workers[0]}"


def test_a_killed_worker_is_replaced_on_its_socket_while_the_other_serves(two_workers):
    url, _, output = two_workers
    killed = _burst_of_connections(url)[0]
    os.kill(killed, signal.SIGKILL)
    for _ in range(3):  # no connection is refused or lost: those hashed to its socket wait for the new one
        workers = _burst_of_connections(url)
        assert killed not in workers
    output.wait_for(f"worker {killed} exited (killed by SIGKILL): starting another on its socket")
    assert len({w for _ in range(ROUNDS) for w in _burst_of_connections(url)}) == 2


def test_a_port_taken_is_refused_not_shared(two_workers, tmp_path):
    url, _, _ = two_workers
    port = url.rsplit(":", 1)[1]
    second = subprocess.run(
        [sys.executable, "-m", "app.cli", "serve", "--port", port, "--workers", "2"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "VANTAGE_DATA_DIR": str(tmp_path)},
    )
    assert second.returncode != 0
    assert f"cannot listen on 127.0.0.1:{port}" in second.stderr
    assert "Address already in use" in second.stderr


def test_the_workers_stop_on_sigterm(tmp_path):
    server, url = launch(tmp_path, "--workers", "2")
    output = Output(server)
    workers = {_burst_of_connections(url)[0] for _ in range(ROUNDS)}
    server.send_signal(signal.SIGTERM)
    assert server.wait(timeout=30) == 0
    output.stop()
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(_alive(pid) for pid in workers)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True
