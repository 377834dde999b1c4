"""`vantage serve --workers 2`, real processes: connections and streams opened in a burst land on
both workers in every round, a killed worker is replaced on its socket while the other serves,
a port already taken is refused rather than shared, and SIGTERM stops every worker, killing one
that hangs.

Each server runs in a session of its own, and every test's servers are ended with everything
in their process group, workers a supervisor left behind included, even when the test fails."""

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import orjson
import pytest
from service import Output
from websockets.sync.client import connect

from app.launch import free_port, stop, wait_until_up
from app.workers import reuse_port_available

pytestmark = pytest.mark.skipif(not reuse_port_available(), reason="SO_REUSEPORT balances only on Linux")

ROUNDS, BURST = 5, 16


class _Servers:
    """`vantage serve` processes, each the leader of a process group of its own (its workers
    are in it); leaving the ``with`` stops each and then kills whatever is left in its group,
    whatever the test did."""

    def __init__(self) -> None:
        self.started: list[tuple[subprocess.Popen, Output | None]] = []

    def __enter__(self) -> "_Servers":
        return self

    def __exit__(self, *_: object) -> None:
        self.end()

    def spawn(
        self, data_dir: Path, port: int, *args: str, stop_seconds: int | None = None
    ) -> subprocess.Popen:
        """``vantage serve --port port args`` with its store in ``data_dir``, its output in a
        pipe; with ``stop_seconds``, the grace period before a stopping worker is killed
        lowered to that (``app.workers.STOP_SECONDS``)."""
        lowered = "" if stop_seconds is None else f"app.workers.STOP_SECONDS = {stop_seconds}; "
        process = subprocess.Popen(
            [
                sys.executable,
                "-c",
                f"import app.workers; {lowered}from app.cli import main; main()",
                "serve",
                "--port",
                str(port),
                *args,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "VANTAGE_DATA_DIR": str(data_dir)},
            start_new_session=True,
        )
        self.started.append((process, None))
        return process

    def start(
        self, data_dir: Path, *args: str, stop_seconds: int | None = None
    ) -> tuple[subprocess.Popen, str, Output]:
        """A server on a free port, once it answers: ``(process, url, output)``."""
        port = free_port()
        process = self.spawn(data_dir, port, *args, stop_seconds=stop_seconds)
        output = Output(process)
        self.started[-1] = (process, output)
        url = f"http://127.0.0.1:{port}"
        try:
            wait_until_up(url, process)
        except RuntimeError as error:
            raise AssertionError(f"{error}; it printed:\n{output}") from None
        return process, url, output

    def end(self) -> None:
        for process, output in reversed(self.started):
            stop(process, timeout=15)
            with contextlib.suppress(ProcessLookupError):  # none left: every worker stopped
                os.killpg(process.pid, signal.SIGKILL)
            if output is not None:
                output.stop()  # reads the rest (the process is reaped already)
            else:
                process.communicate()


@pytest.fixture(scope="module")
def module_servers() -> Iterator[_Servers]:
    with _Servers() as servers:
        yield servers


@pytest.fixture
def servers() -> Iterator[_Servers]:
    with _Servers() as servers:
        yield servers


@pytest.fixture(scope="module")
def two_workers(module_servers, tmp_path_factory):
    """`vantage serve --workers 2`: ``(url, doc, output)``."""
    _, url, output = module_servers.start(
        tmp_path_factory.mktemp("data"), "--workers", "2", "--log-level", "info"
    )
    # It answers once one worker does; the other's socket takes no connection till it listens
    output.wait_for("Application startup complete", times=2)
    doc = httpx.post(f"{url}/documents", json={"name": "spread"}).json()["id"]
    return url, doc, output


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


def test_a_port_taken_is_refused_not_shared(two_workers, servers, tmp_path):
    url, _, _ = two_workers
    port = int(url.rsplit(":", 1)[1])
    second = servers.spawn(tmp_path, port, "--workers", "2")  # ended with its workers, whatever happens
    try:
        out, _ = second.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"a second server started on the taken port {port}") from None
    assert second.returncode != 0
    assert f"vantage serve: port {port} on 127.0.0.1 is in use" in out
    assert "Vantage on http://" not in out


def test_the_workers_stop_on_sigterm(servers, tmp_path):
    server, url, _ = servers.start(tmp_path, "--workers", "2")
    workers = {_burst_of_connections(url)[0] for _ in range(ROUNDS)}
    server.send_signal(signal.SIGTERM)
    assert server.wait(timeout=30) == 0
    _gone(workers)


def test_a_worker_that_hangs_on_sigterm_is_killed_after_the_grace_period(servers, tmp_path):
    """A worker stopped (SIGSTOP: it takes no SIGTERM until it runs again, as one stuck would
    not act on it) is killed once the grace period is over, and the server exits."""
    server, url, output = servers.start(tmp_path, "--workers", "2", "--log-level", "info", stop_seconds=1)
    workers = {_burst_of_connections(url)[0] for _ in range(ROUNDS)}
    hung = min(workers)
    os.kill(hung, signal.SIGSTOP)
    server.send_signal(signal.SIGTERM)
    try:
        assert server.wait(timeout=30) == 0
    except subprocess.TimeoutExpired:
        raise AssertionError(f"the server still waits for worker {hung}; it printed:\n{output}") from None
    output.wait_for(f"worker {hung} did not stop within 1 s: killed")
    _gone(workers)


def _gone(workers: set[int]) -> None:
    """Until none of ``workers`` runs; AssertionError after 10 s."""
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
