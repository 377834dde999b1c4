"""Who may write and read, and the limits: each refusal says why and changes nothing."""

import ipaddress
import os
import subprocess
import sys
import time

import httpx
import orjson
import pytest
from fastapi.testclient import TestClient
from service import NDJSON, client, ndjson, receive
from starlette.websockets import WebSocketDisconnect

from app.config import Settings, get_settings
from app.launch import free_port
from spatial import scenes

GOOD = {"authorization": "Bearer s3cret"}
ITEM = {"x0": 0, "y0": 0, "x1": 1, "y1": 1}


@pytest.fixture
def configure(data_dir, monkeypatch):
    """Set ``VANTAGE_*`` settings for the app under test."""

    def set_env(**values: str) -> None:
        for key, value in values.items():
            monkeypatch.setenv(f"VANTAGE_{key.upper()}", value)
        get_settings.cache_clear()

    return set_env


def test_writes_need_a_token_and_a_refused_one_changes_nothing(configure, tmp_path):
    (tmp_path / "tokens").write_text("# one a line\nfrom-file\n")
    configure(tokens="s3cret, other", tokens_file=str(tmp_path / "tokens"))
    with client() as c:
        missing = c.post("/documents", json={"name": "a"})
        assert missing.status_code == 401 and missing.headers["www-authenticate"] == "Bearer"
        assert "Authorization: Bearer" in missing.json()["detail"]
        wrong = c.post("/documents", json={"name": "a"}, headers={"authorization": "Bearer s3cre"})
        assert wrong.status_code == 403 and "not one this server accepts" in wrong.json()["detail"]
        assert c.get("/documents").json() == []  # reads are open; nothing was created
        doc = c.post("/documents", json={"name": "a"}, headers=GOOD).json()["id"]
        assert (
            c.post(
                "/documents", json={"name": "b"}, headers={"authorization": "Bearer from-file"}
            ).status_code
            == 201
        )
        body = ndjson(scenes.uniform(50, seed=1)[0])
        for method, url, kwargs in [
            ("POST", f"/documents/{doc}/items", {"content": body}),
            ("PUT", f"/documents/{doc}/items/i1", {"json": ITEM}),
            ("DELETE", f"/documents/{doc}/items/i1", {}),
            ("DELETE", f"/documents/{doc}", {}),
        ]:
            assert c.request(method, url, **kwargs).status_code == 401
            assert (
                c.request(method, url, headers={"authorization": "Bearer nope"}, **kwargs).status_code == 403
            )
            assert c.get(f"/documents/{doc}").json()["version"] == 0, (method, url)
        assert (
            c.post(f"/documents/{doc}/items", content=body, headers={**GOOD, **NDJSON}).json()["version"] == 1
        )


def test_reads_can_need_a_token_too(configure):
    configure(tokens="s3cret", read_token="true")
    with client() as c:
        assert c.get("/documents").status_code == 401
        doc = c.post("/documents", json={"name": "a"}, headers=GOOD).json()["id"]
        assert c.get(f"/documents/{doc}/viewport", params=ITEM).status_code == 401
        assert c.get(f"/documents/{doc}/viewport", params=ITEM, headers=GOOD).status_code == 200
        with c.websocket_connect(f"/documents/{doc}/stream") as ws:
            assert "needs a token" in receive(ws)["message"]
            with pytest.raises(WebSocketDisconnect) as closed:
                receive(ws)
            assert closed.value.code == 4401
        with c.websocket_connect(f"/documents/{doc}/stream?token=s3cret") as ws:  # browsers: no headers
            ws.send_text(orjson.dumps({"viewport": [0, 0, 1, 1]}).decode())
            assert receive(ws)["type"] == "view"


def test_limits_are_named_with_their_setting(configure):
    configure(max_items="40", max_stream_rate="5")
    with client() as c:
        doc = c.post("/documents", json={"name": "a"}).json()["id"]
        boxes = scenes.uniform(41, seed=2)[0]
        over = c.post(f"/documents/{doc}/items", content=ndjson(boxes), headers=NDJSON)
        assert over.status_code == 413 and "VANTAGE_MAX_ITEMS" in over.json()["detail"]
        assert c.get(f"/documents/{doc}").json()["version"] == 0
        assert (
            c.post(f"/documents/{doc}/items", content=ndjson(boxes[:40]), headers=NDJSON).status_code == 200
        )
        full = c.put(f"/documents/{doc}/items/one-more", json=ITEM)
        assert full.status_code == 413 and "VANTAGE_MAX_ITEMS" in full.json()["detail"]
        assert c.put(f"/documents/{doc}/items/i3", json=ITEM).status_code == 200  # replacing is fine
        with c.websocket_connect(f"/documents/{doc}/stream") as ws:
            for seq in range(30):
                ws.send_text(orjson.dumps({"seq": seq, "viewport": [0, 0, 1, 1]}).decode())
            messages = []
            while not any(m["type"] == "error" for m in messages):
                messages.append(receive(ws))
            error = next(m for m in messages if m["type"] == "error")
            assert "429" in error["message"] and "VANTAGE_MAX_STREAM_RATE" in error["message"]
            time.sleep(1.2)  # the bucket refills: the stream goes on
            ws.send_text(orjson.dumps({"seq": 99, "viewport": [0, 0, 1, 1]}).decode())
            while (message := receive(ws)).get("seq") != 99:
                assert message["type"] in ("view", "error")
            assert message["type"] == "view"


def _listening(port: int) -> set[str]:
    """The addresses a socket listens on at ``port``, read from the kernel, not from a banner."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as rows:
            for row in list(rows)[1:]:
                local, state = row.split()[1], row.split()[3]
                address, hex_port = local.split(":")
                if state == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                    # each 32-bit word of the address is printed in the host's (little-endian) order
                    words = [bytes.fromhex(address[i : i + 8])[::-1] for i in range(0, len(address), 8)]
                    found.add(str(ipaddress.ip_address(b"".join(words))))
    return found


def test_without_tokens_the_server_stays_on_loopback(tmp_path):
    port = free_port()
    env = {**os.environ, "VANTAGE_DATA_DIR": str(tmp_path), "VANTAGE_TOKENS": ""}
    server = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "serve", "--host", "0.0.0.0", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                assert httpx.get(f"http://127.0.0.1:{port}/health", timeout=1).status_code == 200
                break
            except httpx.TransportError:
                assert server.poll() is None and time.monotonic() < deadline
                time.sleep(0.1)
        assert _listening(port) == {"127.0.0.1"}  # what the kernel says, whatever was printed
    finally:
        server.terminate()
        output = server.communicate(timeout=10)[0]
    assert "serving on 127.0.0.1, not 0.0.0.0" in output and f"http://127.0.0.1:{port}/" in output


def test_cors_allows_only_the_configured_origins(tmp_path):
    from app.main import create_app  # as service.client does: app.main builds an app on import

    settings = Settings(data_dir=tmp_path, cors_origins="https://canvas.example")
    preflight = {"access-control-request-method": "PUT", "access-control-request-headers": "authorization"}
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as c:
        allowed = c.options("/documents", headers={"origin": "https://canvas.example", **preflight})
        assert allowed.headers["access-control-allow-origin"] == "https://canvas.example"
        assert "access-control-allow-credentials" not in allowed.headers
        other = c.options("/documents", headers={"origin": "https://evil.example", **preflight})
        assert "access-control-allow-origin" not in other.headers
        simple = c.get("/documents", headers={"origin": "https://canvas.example"})
        assert simple.status_code == 200
        assert simple.headers["access-control-allow-origin"] == "https://canvas.example"


def test_an_emptied_or_missing_tokens_file_closes_writes_and_never_opens_them(configure, tmp_path):
    tokens = tmp_path / "tokens"
    tokens.write_text("# one a line\n\nfirst\n")
    configure(tokens_file=str(tokens))
    with client() as c:
        assert (
            c.post("/documents", json={"name": "a"}, headers={"authorization": "Bearer first"}).status_code
            == 201
        )
        assert (
            c.post(
                "/documents", json={"name": "a"}, headers={"authorization": "Bearer # one a line"}
            ).status_code
            == 403
        )
        tokens.write_text("")  # mid-rotation: no token is valid, writes are not open
        assert c.post("/documents", json={"name": "a"}).status_code == 401
        assert (
            c.post("/documents", json={"name": "a"}, headers={"authorization": "Bearer first"}).status_code
            == 403
        )
        tokens.unlink()
        missing = c.post("/documents", json={"name": "a"}, headers={"authorization": "Bearer first"})
        assert missing.status_code == 503 and str(tokens) in missing.json()["detail"]
        assert "VANTAGE_TOKENS_FILE" in missing.json()["detail"]
        tokens.write_text("second\n")  # the rotation lands: read again because the file changed
        assert (
            c.post("/documents", json={"name": "a"}, headers={"authorization": "Bearer second"}).status_code
            == 201
        )
        assert (
            c.post("/documents", json={"name": "a"}, headers={"authorization": "Bearer first"}).status_code
            == 403
        )
        assert len(c.get("/documents").json()) == 2


def test_the_token_is_checked_before_the_body_is_read(configure):
    configure(tokens="s3cret")
    with client() as c:
        for method, url in [
            ("POST", "/documents"),
            ("PUT", "/documents/nope/items/a"),
            ("POST", "/documents/nope/items"),
        ]:
            answer = c.request(
                method, url, content=b"{not json" * 1000, headers={"content-type": "application/json"}
            )
            assert answer.status_code == 401, (method, url, answer.text)  # not 404 or 422: nothing was parsed
        assert c.get("/documents").json() == []


def test_only_reads_and_the_stream_take_a_token_in_the_query(configure):
    configure(tokens="s3cret", read_token="true")
    with client() as c:
        assert c.post("/documents?token=s3cret", json={"name": "a"}).status_code == 401
        doc = c.post("/documents", json={"name": "a"}, headers=GOOD).json()["id"]
        assert c.get(f"/documents/{doc}?token=s3cret").status_code == 200
        assert c.delete(f"/documents/{doc}?token=s3cret").status_code == 401
        assert c.get(f"/documents/{doc}").status_code == 401


def test_requests_must_name_this_server_and_writes_come_from_an_allowed_origin(configure):
    configure(cors_origins="https://canvas.example")
    with client() as c:
        for host in ("evil.example", "evil.example:8000", "127.0.0.1.evil.example"):
            refused = c.get("/documents", headers={"host": host})
            assert refused.status_code == 400 and "VANTAGE_ALLOWED_HOSTS" in refused.json()["detail"], host
            assert c.get("/health", headers={"host": host}).status_code == 200  # a balancer's probe
        assert c.get("/documents", headers={"host": "localhost:8000"}).status_code == 200
        assert c.get("/documents", headers={"host": "[::1]:8000"}).status_code == 200
        evil = c.post("/documents", json={"name": "a"}, headers={"origin": "http://evil.example"})
        assert evil.status_code == 403 and "VANTAGE_CORS_ORIGINS" in evil.json()["detail"]
        assert c.get("/documents").json() == []
        for origin in ("https://canvas.example", "http://127.0.0.1"):  # an allowed one; the page's own
            assert c.post("/documents", json={"name": "a"}, headers={"origin": origin}).status_code == 201
        doc = c.get("/documents").json()[0]["id"]
        with c.websocket_connect(f"/documents/{doc}/stream", headers={"origin": "http://evil.example"}) as ws:
            assert "not allowed" in receive(ws)["message"]
            with pytest.raises(WebSocketDisconnect) as closed:
                receive(ws)
            assert closed.value.code == 4403


def test_hosts_can_be_set(configure):
    configure(allowed_hosts="canvas.example")
    with client() as c:
        assert c.get("/documents", headers={"host": "canvas.example"}).status_code == 200
        assert c.get("/documents", headers={"host": "127.0.0.1"}).status_code == 400


def test_an_import_must_say_what_it_is_and_never_as_a_cors_simple_request(configure):
    configure()
    with client() as c:
        doc = c.post("/documents", json={"name": "a"}).json()["id"]
        body = ndjson(scenes.uniform(5, seed=1)[0])
        simple = ("text/plain", "application/x-www-form-urlencoded", "multipart/form-data", None)
        for kind in simple:  # what a page may send anywhere without asking first
            headers = {"content-type": kind} if kind else {}
            answer = c.post(f"/documents/{doc}/items", content=body, headers=headers)
            assert answer.status_code == 415 and "application/x-ndjson" in answer.json()["detail"], kind
        as_json = c.post(
            f"/documents/{doc}/items", content=body, headers={"content-type": "application/json"}
        )
        assert as_json.status_code == 422 and "not a JSON array of items" in as_json.json()["detail"]
        put = c.put(
            f"/documents/{doc}/items/a",
            content=b'{"x0": 0, "y0": 0, "x1": 1, "y1": 1}',
            headers={"content-type": "text/plain"},
        )
        assert put.status_code == 415
        assert c.get(f"/documents/{doc}").json()["version"] == 0
        ok = c.post(
            f"/documents/{doc}/items",
            content=body,
            headers={"content-type": "application/x-ndjson; charset=utf-8"},
        )
        assert ok.status_code == 200


def test_streams_and_documents_are_capped(configure):
    configure(max_streams="2", max_documents="2")
    with client() as c:
        doc = c.post("/documents", json={"name": "a"}).json()["id"]
        assert c.post("/documents", json={"name": "b"}).status_code == 201
        third = c.post("/documents", json={"name": "c"})
        assert third.status_code == 409 and "VANTAGE_MAX_DOCUMENTS" in third.json()["detail"]
        with (
            c.websocket_connect(f"/documents/{doc}/stream") as one,
            c.websocket_connect(f"/documents/{doc}/stream") as two,
        ):
            for ws in (one, two):
                ws.send_text(orjson.dumps({"viewport": [0, 0, 1, 1]}).decode())
                assert receive(ws)["type"] == "view"
            with c.websocket_connect(f"/documents/{doc}/stream") as three:
                assert "VANTAGE_MAX_STREAMS" in receive(three)["message"]
                with pytest.raises(WebSocketDisconnect) as closed:
                    receive(three)
                assert closed.value.code == 1013
        with c.websocket_connect(f"/documents/{doc}/stream") as again:  # the two closed: room again
            again.send_text(orjson.dumps({"viewport": [0, 0, 1, 1]}).decode())
            assert receive(again)["type"] == "view"


def test_every_write_method_needs_a_token_and_an_allowed_origin(configure):
    """PATCH and PUT are writes as POST and DELETE are: no token, no write; another origin, no write."""
    configure(tokens="s3cret")
    with client() as c:
        doc = c.post("/documents", json={"name": "a"}, headers=GOOD).json()["id"]
        assert c.put(f"/documents/{doc}/items/w", json=ITEM, headers=GOOD).status_code == 201
        evil = {**GOOD, "origin": "http://evil.example"}
        for method, path, body in [
            ("PUT", f"/documents/{doc}/items/w", ITEM),
            ("PATCH", f"/documents/{doc}/items/w", {"x1": 5}),
            ("DELETE", f"/documents/{doc}/items/w", None),
            ("POST", "/documents", {"name": "b"}),
        ]:
            assert c.request(method, path, json=body).status_code == 401, method
            assert c.request(method, path, json=body, headers=evil).status_code == 403, method
        assert c.get(f"/documents/{doc}/items/w").json()["x1"] == 1  # nothing changed


def test_a_body_growing_past_its_cap_is_refused_at_the_limit(configure):
    """No Content-Length to refuse it by: a chunked body is counted as it arrives."""
    with client() as c:
        chunks = (b'{"name": "' + b"x" * 10_000 for _ in range(20))  # 200 kB, past the 64 kB cap
        answer = c.post("/documents", content=chunks, headers={"content-type": "application/json"})
        assert answer.status_code == 413 and "VANTAGE_MAX_JSON_BYTES" in answer.json()["detail"]
        assert c.get("/documents").json() == []
