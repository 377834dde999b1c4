"""Replicas on a shared PostgreSQL behind HAProxy, all real: a PostgreSQL server, two `vantage
serve` processes on it (each with its own snapshot cache) and deploy/haproxy.cfg in front.
Any replica answers any document alike; an edit through one reaches a stream held by the
other; ``min_version`` is honoured; a replica killed mid-import leaves nothing partial; a
PostgreSQL restart under load costs reads nothing and writes a clear 503; the simulator runs
through the front without an error."""

import contextlib
import json
import signal
import subprocess
import sys
import threading
import time

import httpx
import orjson
import psycopg
import pytest
from haproxy import haproxy_front
from service import NDJSON, Output, expected, ids_of, ndjson
from websockets.sync.client import connect

from app.launch import launch
from app.stores.postgres import LOG_LOCK
from spatial import scenes

PAGE = (0.0, 0.0, 700.0, 950.0)  # the first page and a margin
CATCH_UP_MS = 300


def _replica(data_dir, database_url: str, *args: str) -> tuple[subprocess.Popen, str, Output]:
    env = {"VANTAGE_DATABASE_URL": database_url, "VANTAGE_CATCH_UP_MS": str(CATCH_UP_MS)}
    process, url = launch(data_dir, "--log-level", "info", *args, env=env)
    return process, url, Output(process)


@pytest.fixture(scope="module")
def cluster(postgres, tmp_path_factory):
    """Two replicas on one new database, and HAProxy in front: ``(front, [a, b], database url)``."""
    url = postgres.new_database("replicas")
    replicas = [_replica(tmp_path_factory.mktemp(f"replica-{name}"), url) for name in "ab"]
    try:
        with haproxy_front([r[1].removeprefix("http://") for r in replicas]) as front:
            yield front, [r[1] for r in replicas], url
    finally:
        for _, _, output in replicas:
            output.stop()


@pytest.fixture(scope="module")
def report(cluster):
    """A 30-page document imported through the front: ``(doc id, boxes)``."""
    front, _, _ = cluster
    boxes, kinds = scenes.long_document(pages=30, seed=4)
    doc = httpx.post(f"{front}/documents", json={"name": "report"}).json()["id"]
    answer = httpx.post(f"{front}/documents/{doc}/items", content=ndjson(boxes, kinds), headers=NDJSON)
    assert answer.status_code == 200 and answer.json()["version"] == 1, answer.text
    return doc, boxes


def _viewport(url: str, doc: str, rect=PAGE, **params) -> httpx.Response:
    return httpx.get(
        f"{url}/documents/{doc}/viewport",
        params={**dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)), "limit": 100_000, **params},
        timeout=30,
    )


def test_any_replica_answers_a_document_imported_through_the_front(cluster, report):
    front, replicas, _ = cluster
    doc, boxes = report
    for url in [front, *replicas]:
        answer = _viewport(url, doc)
        assert answer.status_code == 200, answer.text
        assert answer.json()["version"] == 1 and ids_of(answer.json()["items"]) == expected(boxes, PAGE)


def test_an_edit_through_one_replica_is_pushed_to_a_stream_on_the_other(cluster, report):
    _, (a, b), _ = cluster
    doc, _ = report
    with connect(f"{b.replace('http', 'ws', 1)}/documents/{doc}/stream", open_timeout=10) as ws:
        ws.send(json.dumps({"seq": 1, "viewport": list(PAGE)}))
        first = json.loads(ws.recv(timeout=10))
        assert first["type"] == "view" and first["version"] >= 1
        put = httpx.put(f"{a}/documents/{doc}/items/sticky", json={"x0": 10, "y0": 10, "x1": 60, "y1": 40})
        assert put.status_code == 201, put.text
        version = put.json()["version"]
        pushed = json.loads(ws.recv(timeout=10))  # no request on b: the change log's follower pushes it
    assert pushed["type"] == "edit" and pushed["version"] == version
    assert [item["id"] for item in pushed["enter"]] == ["sticky"]
    # Any replica catches a client up from the version it held, from the store's log
    since = httpx.get(
        f"{b}/documents/{doc}/diff", params={"from": "0,0,700,950", "to": "0,0,700,950", "since": version - 1}
    ).json()
    assert since["version"] == version and [i["id"] for i in since["enter"]] == ["sticky"]


def test_min_version_is_caught_up_with_and_never_answered_older(cluster, report):
    _, (a, b), _ = cluster
    doc, _ = report
    put = httpx.put(f"{a}/documents/{doc}/items/note", json={"x0": 100, "y0": 100, "x1": 120, "y1": 120})
    version = put.json()["version"]
    read = _viewport(b, doc, min_version=version)  # at once after the write, on the other replica
    assert read.status_code == 200 and read.json()["version"] >= version
    assert "note" in ids_of(read.json()["items"])
    ahead = _viewport(b, doc, min_version=version + 100)  # never written: said at once
    assert ahead.status_code == 409, ahead.text[:300]
    assert f"min_version={version + 100}" in ahead.json()["detail"]
    diff = httpx.get(
        f"{b}/documents/{doc}/diff",
        params={"from": "0,0,10,10", "to": "0,0,10,10", "min_version": version + 100},
    )
    assert diff.status_code == 409
    with (
        connect(f"{b.replace('http', 'ws', 1)}/documents/{doc}/stream?min_version={version + 100}") as ws,
        pytest.raises(Exception, match="4409"),
    ):
        while True:
            ws.recv(timeout=10)


def test_a_replica_killed_mid_import_leaves_nothing_partial(cluster, report, tmp_path):
    _, (a, b), database_url = cluster
    doc, boxes = report
    before = httpx.get(f"{b}/documents/{doc}").json()
    process, url, output = _replica(tmp_path / "c", database_url)
    body = ndjson(scenes.long_document(pages=300, seed=5)[0] + 3.0)
    try:

        def big_import() -> None:
            with contextlib.suppress(httpx.TransportError):  # the replica dies under it, as intended
                httpx.post(f"{url}/documents/{doc}/items", content=body, headers=NDJSON, timeout=60)

        # Hold the change log's lock: the import, its base copied in, parks at its last step
        # before the commit, so the kill lands inside its transaction however fast the machine
        with psycopg.connect(database_url, autocommit=True) as holder:
            holder.execute("SELECT pg_advisory_lock(%s)", (LOG_LOCK,))
            importer = threading.Thread(target=big_import)
            importer.start()
            output.wait_for(f"import into {doc}: storing")  # inside the store's transaction now
            _wait_for(lambda: _waiting_for_the_log(holder), "the import waiting to append to the log", 60)
            process.send_signal(signal.SIGKILL)
            importer.join()
            holder.execute("SELECT pg_advisory_unlock(%s)", (LOG_LOCK,))
    finally:
        output.stop()
    assert httpx.get(f"{b}/documents/{doc}").json()["version"] == before["version"]
    with psycopg.connect(database_url) as db:
        logged = db.execute("SELECT max(version) FROM changes WHERE doc_id = %s", (doc,)).fetchone()[0]
    assert logged == before["version"]
    assert ids_of(_viewport(b, doc, rect=(3, 3, 703, 953)).json()["items"]) >= expected(
        boxes, (3, 3, 703, 953)
    )
    # The dead replica's lock went with its connection: the document takes writes again
    put = httpx.put(f"{a}/documents/{doc}/items/after", json={"x0": 0, "y0": 0, "x1": 1, "y1": 1})
    assert put.status_code == 201 and put.json()["version"] == before["version"] + 1, put.text


def test_a_postgres_restart_under_load_costs_reads_nothing_and_writes_a_clear_503(cluster, report, postgres):
    front, (a, b), _ = cluster
    doc, _ = report
    statuses: list[int] = []
    stop = threading.Event()

    def read() -> None:  # the load: reads through the front and each replica, all along
        with httpx.Client(timeout=30) as http:
            while not stop.is_set():
                for url in (front, a, b):
                    params = dict(zip(("x0", "y0", "x1", "y1"), PAGE, strict=True))
                    statuses.append(http.get(f"{url}/documents/{doc}/viewport", params=params).status_code)

    reader = threading.Thread(target=read)
    reader.start()
    try:
        time.sleep(0.3)
        postgres.stop()
        for url in (a, b):
            _wait_for(lambda url=url: httpx.get(f"{url}/health").json()["status"] == "degraded", "degraded")
        # A client that waits longer than the store's pool (5 s) still gets the 503, not its own timeout.
        box = {"x0": 0, "y0": 0, "x1": 1, "y1": 1}
        refused = httpx.put(f"{a}/documents/{doc}/items/down", json=box, timeout=30)
        assert refused.status_code == 503 and "PostgreSQL" in refused.json()["detail"], refused.text
        assert "retry-after" in refused.headers
        assert httpx.post(f"{front}/documents", json={"name": "x"}, timeout=30).status_code == 503
        # A version b cannot confirm while its store is away: tried for CATCH_UP_MS, then 503
        held = httpx.get(f"{b}/documents/{doc}").json()["version"]
        started = time.monotonic()
        behind = _viewport(b, doc, min_version=held + 1)
        assert behind.status_code == 503 and behind.headers["retry-after"] == "1", behind.text[:300]
        assert "min_version" in behind.json()["detail"] and time.monotonic() - started >= CATCH_UP_MS / 1000
        time.sleep(0.5)  # reads go on meanwhile
        postgres.start()
        for url in (a, b):
            _wait_for(lambda url=url: httpx.get(f"{url}/health").json()["status"] == "ok", "ok again")
    finally:
        stop.set()
        reader.join()
        if postgres.pid is None:  # a failure above: the server the other tests share comes back
            postgres.start()
    assert statuses and set(statuses) == {200}, sorted(set(statuses))
    put = httpx.put(f"{a}/documents/{doc}/items/back", json={"x0": 5, "y0": 5, "x1": 9, "y1": 9})
    assert put.status_code == 201, put.text
    read = _viewport(b, doc, min_version=put.json()["version"])  # b caught up by itself
    assert (
        read.status_code == 200
        and "back" in ids_of(read.json()["items"])
        and "down" not in ids_of(read.json()["items"])
    )


def test_a_write_waiting_on_another_replicas_document_lock_holds_up_no_other_document(cluster):
    """PostgreSQL locks a write's document, not the store: while a document's row is locked
    (another replica's long import, here a transaction the test holds), a write to it waits
    and a write to another document on the same replica goes through."""
    _, (a, _), database_url = cluster
    busy, free = (httpx.post(f"{a}/documents", json={"name": n}).json()["id"] for n in ("busy", "free"))
    box = {"x0": 0, "y0": 0, "x1": 1, "y1": 1}
    answers: dict[str, httpx.Response] = {}
    with psycopg.connect(database_url) as holder:
        holder.execute("SELECT 1 FROM documents WHERE id = %s FOR UPDATE", (busy,))
        waiting = threading.Thread(
            target=lambda: answers.setdefault(
                "busy", httpx.put(f"{a}/documents/{busy}/items/n", json=box, timeout=60)
            )
        )
        waiting.start()
        time.sleep(0.3)  # the write to busy is waiting on the row now
        started = time.monotonic()
        other = httpx.put(f"{a}/documents/{free}/items/n", json=box, timeout=60)
        took = time.monotonic() - started
        assert other.status_code == 201 and took < 2, (other.status_code, took)
        assert "busy" not in answers  # still waiting on the row
        holder.rollback()
    waiting.join()
    assert answers["busy"].status_code == 201 and answers["busy"].json()["version"] == 1


def test_the_simulator_runs_through_the_front_without_an_error(cluster, report, tmp_path):
    front, _, _ = cluster
    doc, _ = report
    run = subprocess.run(
        [sys.executable, "-m", "app.simulate", "--url", front, "--doc", doc, "--seconds", "1.5",
         "--users", "2", "--overscan", "0.5", "--lod", "on", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    modes = orjson.loads((tmp_path / "result.json").read_bytes())["modes"]
    assert {m["transport"] for m in modes} == {"poll", "diff", "stream"}
    for m in modes:
        assert m["errors"] == 0 and m["requests"] > 0, m


def _waiting_for_the_log(db: psycopg.Connection) -> bool:
    query = "SELECT count(*) FROM pg_locks WHERE locktype = 'advisory' AND objid = %s AND NOT granted"
    return db.execute(query, (LOG_LOCK,)).fetchone()[0] > 0


def _wait_for(condition, what: str, timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            if condition():
                return
        except httpx.HTTPError:
            pass
        assert time.monotonic() < deadline, f"not {what} within {timeout:g} s"
        time.sleep(0.1)
