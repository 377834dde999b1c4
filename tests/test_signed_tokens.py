"""Signed access tokens (JWT) against real `vantage serve` processes: each route grants or refuses
by the token's `docs` claim and scope, the wildcard, `create`, expiry (also mid-stream, and a
renewal before it), forged and `alg: none` tokens, the wrong algorithm for the key, a rotation's
two secrets, the audience, the filtered list, and static tokens as full-access keys."""

import base64
import hashlib
import hmac
import json
import os
import subprocess
import sys
import time

import httpx
import jwt
import orjson
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519
from service import NDJSON, ROOT, Output, ndjson
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

import app.client
import app.routers.documents
from app.access import EXPIRED, FORGED, UNREADABLE, mint
from app.cli import main
from app.client import Client, Stream
from app.config import get_settings
from app.launch import launch
from spatial import scenes

NEW, OLD = "n" * 16 + "e" * 16 + "w" * 8, "o" * 40  # a rotation: the new secret first, the old still accepted
STATIC = {"authorization": "Bearer backend-key"}
VIEW = {"x0": 0, "y0": 0, "x1": 1000, "y1": 1000}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A server taking static token `backend-key` and tokens signed with NEW or OLD; two documents:
    ``(url, a, b, output)``."""
    env = {"VANTAGE_TOKENS": "backend-key", "VANTAGE_JWT_SECRET": f"{NEW},{OLD}"}
    process, url = launch(tmp_path_factory.mktemp("data"), "--log-level", "info", env=env)
    output = Output(process)
    try:
        docs = [httpx.post(f"{url}/documents", json={"name": n}, headers=STATIC).json()["id"] for n in "ab"]
        for doc in docs:
            body = ndjson(scenes.uniform(300, seed=3)[0])
            httpx.post(
                f"{url}/documents/{doc}/items", content=body, headers={**STATIC, **NDJSON}
            ).raise_for_status()
        yield url, *docs, output
    finally:
        output.stop()


def _bearer(token: str) -> dict[str, str]:
    return {"authorization": f"Bearer {token}"}


def _reads(url: str, doc: str, token: str) -> list[int]:
    """The status of every read route of ``doc`` with ``token``."""
    with httpx.Client(base_url=url, headers=_bearer(token)) as c:
        return [
            c.get(f"/documents/{doc}").status_code,
            c.get(f"/documents/{doc}/viewport", params=VIEW).status_code,
            c.get(f"/documents/{doc}/diff", params={"from": "0,0,10,10", "to": "5,5,15,15"}).status_code,
            c.get(f"/documents/{doc}/search", params={"q": "x"}).status_code,
            c.get(f"/documents/{doc}/items").status_code,
            c.get(f"/documents/{doc}/items/i0").status_code,
            c.get(f"/documents/{doc}/cells", params={**VIEW, "cell": 100}).status_code,
        ]


def _writes(url: str, doc: str, token: str) -> list[int]:
    with httpx.Client(base_url=url, headers=_bearer(token)) as c:
        return [
            c.put(f"/documents/{doc}/items/w", json={"x0": 1, "y0": 1, "x1": 2, "y1": 2}).status_code,
            c.patch(f"/documents/{doc}/items/w", json={"x1": 3}).status_code,
            c.delete(f"/documents/{doc}/items/w").status_code,
        ]


def test_a_read_grant_reads_its_document_only_and_writes_nothing(server):
    url, a, b, _ = server
    token = mint(NEW, {a: "read"}, 600)
    assert _reads(url, a, token) == [200] * 7
    assert set(_reads(url, b, token)) == {403}
    assert set(_writes(url, a, token)) == {403}
    refused = httpx.get(f"{url}/documents/{b}/viewport", params=VIEW, headers=_bearer(token))
    assert f"does not allow reading document {b!r}" in refused.json()["detail"]
    assert token not in refused.text


def test_a_write_grant_writes_and_reads_and_the_wildcard_covers_every_document(server):
    url, a, b, _ = server
    assert _writes(url, a, mint(NEW, {a: "write"}, 600)) == [201, 200, 200]
    assert set(_writes(url, b, mint(NEW, {a: "write"}, 600))) == {403}
    everything = mint(NEW, {"*": "read"}, 600)
    assert _reads(url, a, everything) == _reads(url, b, everything) == [200] * 7
    assert set(_writes(url, b, everything)) == {403}
    assert _writes(url, b, mint(NEW, {"*": "read", b: "write"}, 600)) == [201, 200, 200]


def test_the_wildcard_write_grant_writes_every_document(server):
    url, a, b, _ = server
    everything = mint(NEW, {"*": "write"}, 600)
    assert _writes(url, a, everything) == _writes(url, b, everything) == [201, 200, 200]


def test_creating_and_deleting_need_their_grants(server):
    url, a, _, _ = server
    plain, creator = mint(NEW, {a: "write"}, 600), mint(NEW, {}, 600, create=True)
    assert httpx.post(f"{url}/documents", json={"name": "c"}, headers=_bearer(plain)).status_code == 403
    made = httpx.post(f"{url}/documents", json={"name": "c"}, headers=_bearer(creator))
    assert made.status_code == 201
    doc = made.json()["id"]
    assert (
        httpx.delete(f"{url}/documents/{doc}", headers=_bearer(mint(NEW, {doc: "read"}, 600))).status_code
        == 403
    )
    assert (
        httpx.delete(f"{url}/documents/{doc}", headers=_bearer(mint(NEW, {doc: "write"}, 600))).status_code
        == 204
    )


def test_creating_needs_the_claim_create_true_exactly(server):
    url, _, _, _ = server
    for claim in ("no", 1, "true", [True]):  # truthy, but not `true`
        token = jwt.encode(
            {"docs": {}, "create": claim, "exp": int(time.time()) + 60}, NEW, algorithm="HS256"
        )
        refused = httpx.post(f"{url}/documents", json={"name": "c"}, headers=_bearer(token))
        assert refused.status_code == 403, (claim, refused.text)
        assert refused.json()["detail"] == (
            "the token does not allow creating documents (its claim `create` is not true)"
        )


def test_the_list_shows_what_the_token_reads(server):
    url, a, b, _ = server
    listed = lambda token: [d["id"] for d in httpx.get(f"{url}/documents", headers=_bearer(token)).json()]
    assert listed(mint(NEW, {b: "read"}, 600)) == [b]
    assert listed(mint(NEW, {a: "write", "nosuch": "read"}, 600)) == [a]
    assert set(listed(mint(NEW, {"*": "read"}, 600))) >= {a, b}
    assert listed(mint(NEW, {}, 600)) == []
    assert {a, b} <= {d["id"] for d in httpx.get(f"{url}/documents", headers=STATIC).json()}


def test_missing_expired_forged_malformed_and_unsigned_tokens_are_401_saying_why(server):
    url, a, _, _ = server
    path = f"{url}/documents/{a}/viewport"
    assert (
        httpx.get(path, params=VIEW).json()["detail"]
        == "this needs a token: send `Authorization: Bearer <token>`"
    )
    expired = jwt.encode({"docs": {a: "read"}, "exp": int(time.time()) - 5}, NEW, algorithm="HS256")
    forged = mint("f" * 40, {a: "read"}, 600)
    good = mint(NEW, {a: "read"}, 600)
    tampered = (
        good[: good.rindex(".") + 1] + good[good.rindex(".") + 1 : -2]
    )  # PyJWT: "Invalid crypto padding"
    no_exp = jwt.encode({"docs": {a: "read"}}, NEW, algorithm="HS256")
    claims = base64.urlsafe_b64encode(json.dumps({"docs": {a: "write"}, "exp": 2**40}).encode()).rstrip(b"=")
    unsigned = b"eyJhbGciOiJub25lIiwidHlwIjoiSldUIn0." + claims + b"."  # alg: none
    bad_docs = jwt.encode({"docs": {a: "admin"}, "exp": int(time.time()) + 60}, NEW, algorithm="HS256")
    for token, why in [
        (expired, EXPIRED),
        (forged, FORGED),
        (tampered, FORGED),
        ("not-a-key", UNREADABLE),  # malformed: 401 like every token that is not a valid one
        ("a.b.c", UNREADABLE),
        (good.rpartition(".")[0], UNREADABLE),
        (no_exp, "the token has no `exp` claim: a signed token must say when it expires"),
        (unsigned.decode(), "the token's `alg` is not HS256, the one algorithm this server's key verifies"),
        (
            bad_docs,
            "the token's claims cannot be used: `docs` gives {a!r} 'admin': a right is 'read' or 'write'",
        ),
    ]:
        answer = httpx.get(path, params=VIEW, headers=_bearer(token))
        assert answer.status_code == 401, (why, answer.text)
        assert answer.json()["detail"] == why.format(a=a), answer.text
        assert answer.headers["www-authenticate"] == "Bearer" and token not in answer.text
    assert httpx.get(path, params={**VIEW, "token": forged}).status_code == 401  # in the query too


def test_an_expired_signed_token_is_401_also_one_verified_and_cached_while_valid(server):
    url, a, _, _ = server
    token = mint(NEW, {a: "write"}, 2)
    assert _reads(url, a, token)[:1] == [200] and _writes(url, a, token)[:1] == [201]  # verified, kept
    expires = jwt.decode(token, options={"verify_signature": False})["exp"]
    time.sleep(max(expires - time.time(), 0) + 0.1)
    assert set(_reads(url, a, token)) == set(_writes(url, a, token)) == {401}
    answer = httpx.get(f"{url}/documents/{a}", headers=_bearer(token))
    assert answer.json()["detail"] == EXPIRED


def test_both_secrets_of_a_rotation_and_static_tokens_are_accepted(server):
    url, a, b, output = server
    assert _reads(url, a, mint(OLD, {a: "read"}, 600)) == [200] * 7
    assert _reads(url, b, "backend-key") == [200] * 7  # a static token: every document
    assert httpx.get(f"{url}/documents/{a}", headers=_bearer("not-a-key")).status_code == 401
    who = mint(NEW, {a: "write"}, 600, subject="user-42")
    assert _writes(url, a, who) == [201, 200, 200]
    output.wait_for(f"PUT /documents/{a}/items/w by user-42")  # who did it, never the token
    assert who not in str(output)


def test_a_stream_closes_when_its_token_expires_unless_renewed(server):
    url, a, b, _ = server
    ws_url = f"{url.replace('http', 'ws')}/documents/{a}/stream"
    view = orjson.dumps({"seq": 1, "viewport": list(VIEW.values())}).decode()
    with connect(f"{ws_url}?token={mint(NEW, {a: 'read'}, 2)}", open_timeout=10) as ws:
        ws.send(view)
        assert orjson.loads(ws.recv(timeout=10))["type"] == "view"
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                assert orjson.loads(ws.recv(timeout=10))["type"] == "error"
        assert closed.value.rcvd.code == 4401
    with connect(ws_url, additional_headers=_bearer(mint(NEW, {a: "read"}, 2)), open_timeout=10) as ws:
        ws.send(view)
        assert orjson.loads(ws.recv(timeout=10))["type"] == "view"
        ws.send(orjson.dumps({"token": mint(NEW, {b: "read"}, 600)}).decode())  # not this document's
        assert "does not allow reading" in orjson.loads(ws.recv(timeout=10))["message"]
        ws.send(orjson.dumps({"token": mint(NEW, {a: "read"}, 600)}).decode())
        time.sleep(3)  # past the first token's expiry
        ws.send(orjson.dumps({"seq": 2, "viewport": [0, 0, 5, 5]}).decode())
        assert orjson.loads(ws.recv(timeout=10))["seq"] == 2  # still open
    with connect(f"{ws_url}?token={mint(NEW, {b: 'read'}, 60)}", open_timeout=10) as ws:  # another's
        assert "does not allow reading" in orjson.loads(ws.recv(timeout=10))["message"]
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=10)
        assert closed.value.rcvd.code == 4403


def test_a_public_key_pins_its_algorithm_and_the_audience_is_checked(tmp_path):
    private = ed25519.Ed25519PrivateKey.generate()
    pem = tmp_path / "key.pem"
    pem.write_bytes(
        private.public_key().public_bytes(
            serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
        )
    )
    env = {"VANTAGE_JWT_PUBLIC_KEY": str(pem), "VANTAGE_JWT_AUDIENCE": "vantage-test"}
    process, url = launch(tmp_path / "data", env=env)
    output = Output(process)
    try:
        exp = int(time.time()) + 600
        creator = jwt.encode(
            {"docs": {}, "create": True, "exp": exp, "aud": "vantage-test"}, private, algorithm="EdDSA"
        )
        made = httpx.post(f"{url}/documents", json={"name": "k"}, headers=_bearer(creator))
        assert made.status_code == 201, made.text
        doc = made.json()["id"]
        good = jwt.encode(
            {"docs": {doc: "read"}, "exp": exp, "aud": "vantage-test"}, private, algorithm="EdDSA"
        )
        assert httpx.get(f"{url}/documents/{doc}", headers=_bearer(good)).status_code == 200
        other_aud = jwt.encode(
            {"docs": {doc: "read"}, "exp": exp, "aud": "elsewhere"}, private, algorithm="EdDSA"
        )
        no_aud = jwt.encode({"docs": {doc: "read"}, "exp": exp}, private, algorithm="EdDSA")
        # HS256 keyed with the public key's own PEM bytes: the confusion a pinned algorithm refuses
        confused = _hs256({"docs": {doc: "read"}, "exp": exp, "aud": "vantage-test"}, pem.read_bytes())
        for token in (other_aud, no_aud, confused):
            assert httpx.get(f"{url}/documents/{doc}", headers=_bearer(token)).status_code == 401
    finally:
        output.stop()


def _hs256(claims: dict, key: bytes) -> str:
    """A token signed with HMAC-SHA256 under ``key``, written by hand (PyJWT refuses a PEM as an HMAC key)."""
    encode = lambda data: base64.urlsafe_b64encode(data).rstrip(b"=")
    signing = encode(b'{"alg":"HS256","typ":"JWT"}') + b"." + encode(json.dumps(claims).encode())
    return (signing + b"." + encode(hmac.new(key, signing, hashlib.sha256).digest())).decode()


SHORT = "VANTAGE_JWT_SECRET: secret 2 of 2 is under 32 bytes: make each at least 32 random bytes (e.g. `openssl rand -hex 32`)"


def test_a_short_secret_or_a_bad_key_stops_the_server_at_start_saying_which(tmp_path):
    for env, said in [
        ({"VANTAGE_JWT_SECRET": f"{NEW}, {'s' * 31}"}, f"vantage serve: {SHORT}\n"),  # a byte short
        ({"VANTAGE_JWT_PUBLIC_KEY": str(tmp_path / "missing.pem")}, "not a PEM public key"),
    ]:
        done = subprocess.run(
            [sys.executable, "-m", "app.cli", "serve", "--port", "0", "--workers", "1"],
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "VANTAGE_DATA_DIR": str(tmp_path), **env},
        )
        assert done.returncode != 0 and said in done.stderr, done.stderr[-2000:]
        assert "Traceback" not in done.stderr


def test_vantage_token_refuses_a_secret_the_server_refuses_in_the_servers_words(monkeypatch, capsys):
    monkeypatch.setenv("VANTAGE_JWT_SECRET", f"{NEW}, {'s' * 31}")
    get_settings.cache_clear()
    try:
        with pytest.raises(SystemExit) as stop:
            main(["token", "--doc", "d1"])
    finally:
        get_settings.cache_clear()
    assert stop.value.code == 2
    assert capsys.readouterr() == ("", f"vantage token: {SHORT}\n")


def test_vantage_token_mints_what_the_server_accepts(server, monkeypatch, capsys):
    url, a, b, _ = server
    monkeypatch.setenv("VANTAGE_JWT_SECRET", f"{NEW},{OLD}")
    get_settings.cache_clear()
    main(["token", "--doc", f"{a}:write", "--ttl", "10m", "--sub", "script"])
    token = capsys.readouterr().out.strip()
    assert _writes(url, a, token) == [201, 200, 200] and set(_reads(url, b, token)) == {403}
    claims = jwt.decode(token, NEW, algorithms=["HS256"])
    assert claims["sub"] == "script" and 590 <= claims["exp"] - time.time() <= 601
    get_settings.cache_clear()


def test_the_python_client_renews_a_token_from_a_function_and_pages_the_list(server, monkeypatch):
    url, a, b, _ = server
    monkeypatch.setattr(app.client, "RENEW_SECONDS", 3.0)
    minted = []

    def fresh() -> str:
        minted.append(mint(NEW, {a: "read"}, 4))  # due for renewal a second after it is made
        return minted[-1]

    with Client(url, token=fresh) as c, Stream(url, a, token=fresh) as stream:
        started = time.monotonic()
        while time.monotonic() - started < 7:  # past the first tokens' expiry, renewing as it goes
            assert c.describe(a)["id"] == a
            assert stream.view((0, 0, 100, 100))["type"] == "view" and not stream.errors
            time.sleep(0.5)
    assert len(minted) >= 6
    with Client(url, token="backend-key") as c:  # a list's pages followed through its Link header
        assert [d["id"] for d in c._call("GET", "/documents?limit=1", app.client._page)][:2] == [a, b]


def test_the_access_example_in_the_docs_runs_as_written(server, monkeypatch):
    """The Python block of docs/operating.md's "Access for many users", as it is."""
    url, _, _, _ = server
    page = (ROOT / "docs" / "operating.md").read_text()
    section = page[page.index("## Access for many users") :]
    block = section[section.index("```python\n") + len("```python\n") :]
    block = block[: block.index("```")]
    env = {"VANTAGE_URL": url, "VANTAGE_TOKEN": "backend-key", "VANTAGE_JWT_SECRET": f"{NEW},{OLD}"}
    done = subprocess.run(
        [sys.executable, "-c", block],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        env={**os.environ, **env},
    )
    assert done.returncode == 0, done.stderr[-3000:]
