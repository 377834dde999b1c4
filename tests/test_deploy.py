"""The parts the replicas' tests stand on, each real: the session's PostgreSQL server
(tests/postgres.py, the ``postgres`` fixture) and HAProxy with deploy/haproxy.cfg
(tests/haproxy.py) in front of tiny replicas that answer with their own names."""

import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections import Counter
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import psycopg
import pytest
from haproxy import haproxy_front
from websockets.sync.client import connect as websocket

from app.launch import free_port, wait_until_up

# -- PostgreSQL ------------------------------------------------------------------------------------


def test_postgres_keeps_committed_rows_across_a_restart(postgres):
    url = postgres.url
    with psycopg.connect(url) as connection:
        connection.execute("CREATE TABLE notes (id int PRIMARY KEY, text text NOT NULL)")
        connection.execute("INSERT INTO notes VALUES (1, 'kept ✓')")
    postgres.stop()
    with pytest.raises(psycopg.OperationalError):
        psycopg.connect(url, connect_timeout=2).close()
        pytest.fail("a connection succeeded while the server was stopped")
    postgres.start()
    assert postgres.url == url, "the URL changed across the restart"
    with psycopg.connect(url) as connection:
        rows = connection.execute("SELECT id, text FROM notes").fetchall()
    assert rows == [(1, "kept ✓")], "the committed row did not survive the restart"


def test_postgres_runs_unprivileged_with_the_settings_the_tests_need(postgres):
    with psycopg.connect(postgres.url) as connection:
        backend = connection.execute("SELECT pg_backend_pid()").fetchone()[0]
        settings = {
            name: connection.execute(f"SHOW {name}").fetchone()[0]
            for name in ("max_connections", "server_encoding", "fsync")
        }
        # While the session is open: its backend exits when it closes.
        uids = {
            "the postmaster": (postgres.pid, _uids(postgres.pid)),
            "a session's backend": (backend, _uids(backend)),
        }
    assert settings == {"max_connections": "200", "server_encoding": "UTF8", "fsync": "off"}
    expected = os.geteuid() or (postgres.data.stat().st_uid)  # as root: the data's owner
    for role, (pid, ids) in uids.items():
        assert 0 not in ids, f"{role} (pid {pid}) runs as root: uids {ids}"
        assert set(ids) == {expected}, f"{role} (pid {pid}) runs as {ids}, not uid {expected}"


def _uids(pid: int) -> list[int]:
    """Real, effective, saved and filesystem uids of a process."""
    status = Path(f"/proc/{pid}/status").read_text()
    line = next(line for line in status.splitlines() if line.startswith("Uid:"))
    return [int(uid) for uid in line.split()[1:]]


# -- HAProxy ---------------------------------------------------------------------------------------

# A replica in miniature: it answers every HTTP path with its name and what it was asked, and
# a WebSocket with its name, then echoes.
REPLICA = """
import json, sys
import uvicorn

NAME, PORT = sys.argv[1], int(sys.argv[2])

async def app(scope, receive, send):
    if scope["type"] == "http":
        headers = dict(scope["headers"])
        body = {
            "replica": NAME,
            "path": scope["path"],
            "query": scope["query_string"].decode(),
            "forwarded_for": headers.get(b"x-forwarded-for", b"").decode(),
        }
        await send({"type": "http.response.start", "status": 200,
                    "headers": [(b"content-type", b"application/json")]})
        await send({"type": "http.response.body", "body": json.dumps(body).encode()})
    elif scope["type"] == "websocket":
        await receive()
        await send({"type": "websocket.accept"})
        await send({"type": "websocket.send", "text": NAME})
        while (message := await receive())["type"] == "websocket.receive":
            await send({"type": "websocket.send", "text": message["text"]})

uvicorn.run(app, host="127.0.0.1", port=PORT, lifespan="off", log_level="warning")
"""

DIRECT = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # never an HTTP proxy
DOCUMENTS = [f"d{n:03d}" for n in range(40)]


@contextmanager
def replicas(directory: Path, names: list[str]) -> Iterator[dict[str, subprocess.Popen]]:
    """One miniature replica process per name, each answering on its port: ``{address: process}``
    in the order of ``names``. Killed on exit."""
    started: dict[str, subprocess.Popen] = {}
    try:
        for name in names:
            port = free_port()
            log = (directory / f"{name}.log").open("wb")
            started[f"127.0.0.1:{port}"] = subprocess.Popen(
                [sys.executable, "-c", REPLICA, name, str(port)], stdout=log, stderr=subprocess.STDOUT
            )
            log.close()
        for (address, process), name in zip(started.items(), names, strict=True):
            _wait_for(f"http://{address}/health", process, directory / f"{name}.log")
        yield started
    finally:
        for process in started.values():
            process.kill()
            process.wait()


@pytest.fixture(scope="module")
def front(tmp_path_factory):
    with ExitStack() as stack:
        backends = stack.enter_context(replicas(tmp_path_factory.mktemp("replicas"), ["one", "two"]))
        yield stack.enter_context(haproxy_front(list(backends)))


def get(url: str) -> dict:
    """The JSON of a 200 answer; AssertionError naming the URL and what came instead."""
    try:
        with DIRECT.open(url, timeout=5) as answer:
            return json.loads(answer.read())
    except urllib.error.HTTPError as error:
        raise AssertionError(f"GET {url}: {error.code} {error.read()[:500]!r}") from None
    except OSError as error:
        raise AssertionError(f"GET {url}: {error}") from None


def test_each_document_is_served_by_one_replica_whatever_its_sub_path_or_query(front):
    for doc in DOCUMENTS[:10]:
        paths = [
            f"/documents/{doc}",
            *(f"/documents/{doc}/viewport?x0=0&y0=0&x1={k}&y1={k}" for k in (10, 20, 30)),
            *(f"/documents/{doc}/diff?since={k}" for k in (1, 2)),
            f"/documents/{doc}/items/i1",
        ]
        answers = {path: get(f"{front}{path}") for path in paths}
        served = {path: answer["replica"] for path, answer in answers.items()}
        assert len(set(served.values())) == 1, f"{doc}'s requests went to several replicas: {served}"
        for path, answer in answers.items():
            assert f"{answer['path']}?{answer['query']}".rstrip("?") == path, "the request changed on its way"
            assert answer["forwarded_for"] == "127.0.0.1", f"X-Forwarded-For: {answer['forwarded_for']!r}"


def test_documents_spread_over_the_replicas(front):
    served = Counter(get(f"{front}/documents/{doc}/viewport")["replica"] for doc in DOCUMENTS)
    assert set(served) == {"one", "two"}, f"{len(DOCUMENTS)} documents went to {dict(served)} only"


def test_a_websocket_passes_through_to_the_documents_replica(front):
    replica = get(f"{front}/documents/d001/viewport")["replica"]
    with websocket(f"{front.replace('http', 'ws', 1)}/documents/d001/stream", open_timeout=5) as stream:
        assert stream.recv(timeout=5) == replica, "the stream reached another replica than the document's"
        for text in ("first", "second " * 1000):
            stream.send(text)
            assert stream.recv(timeout=5) == text, "the stream did not echo through haproxy"


def test_a_dead_replicas_documents_move_to_the_others_and_no_other_document_moves(tmp_path):
    """Three replicas (a copy of the configuration with one server line added); one is killed.
    Retries with redispatch answer its documents at once (not after a second's wait), the health checks mark it down
    within about 2 s (fall 2, inter 1s), and through both, consistent hashing keeps every other
    document where it was."""
    with replicas(tmp_path, ["one", "two", "three"]) as backends, haproxy_front(list(backends)) as front:
        owner = {doc: get(f"{front}/documents/{doc}")["replica"] for doc in DOCUMENTS}
        assert set(owner.values()) == {"one", "two", "three"}, f"not every replica got documents: {owner}"
        victim_name = owner[DOCUMENTS[0]]
        victim = list(backends.values())[["one", "two", "three"].index(victim_name)]
        victim.send_signal(signal.SIGKILL)
        victim.wait()
        killed = time.monotonic()
        rounds = 0
        while time.monotonic() - killed < 3.0:  # past the checks' 2 s, so both phases are seen
            rounds += 1
            for doc in DOCUMENTS:
                sent = time.monotonic()
                replica = get(f"{front}/documents/{doc}/viewport")["replica"]
                took = time.monotonic() - sent
                if owner[doc] == victim_name:
                    assert replica != victim_name, f"{doc} answered by the killed replica {victim_name}"
                    assert took < 0.8, f"{doc} took {took:.1f} s: it waited to retry on the dead replica"
                else:
                    assert replica == owner[doc], (
                        f"{doc} moved from {owner[doc]} to {replica} when {victim_name} died "
                        f"({time.monotonic() - killed:.1f} s after): the hashing is not consistent"
                    )
        assert rounds > 3, f"only {rounds} rounds of requests in 3 s"


def _wait_for(url: str, process: subprocess.Popen, log: Path, timeout: float = 20) -> None:
    try:
        wait_until_up(url, process, timeout, path="")
    except RuntimeError as error:
        raise AssertionError(f"{error}; it printed:\n{log.read_text()}") from None
