"""Uploads: an import sent in parts and committed as one, all or nothing. Parts cut anywhere
(mid-line, mid-gzip) make the same document as one body; a missing part refuses the commit and
a part sent again replaces itself; a bad line is named and loses nothing; a server killed
mid-upload stores nothing; every answer is compared with brute force."""

import gzip
import signal
import subprocess
import sys

import httpx
import numpy as np
import orjson
import pytest
from service import NDJSON, client, expected, ids_of, ndjson

from app.errors import NotFound
from app.launch import launch, stop
from spatial import scenes

ALL = {"x0": -1e9, "y0": -1e9, "x1": 1e9, "y1": 1e9, "limit": 100_000}


def _cut(body: bytes, parts: int, seed: int = 0) -> list[bytes]:
    """``body`` cut at ``parts - 1`` random places: mid-line, mid-number, anywhere."""
    cuts = sorted(np.random.default_rng(seed).choice(np.arange(1, len(body)), parts - 1, replace=False))
    return [body[a:b] for a, b in zip([0, *cuts], [*cuts, len(body)], strict=True)]


def _upload(c, doc: str, parts: list[bytes], **options) -> str:
    made = c.post(f"/documents/{doc}/uploads", json=options)
    assert made.status_code == 201, made.text
    upload = made.json()["id"]
    for number, part in enumerate(parts, 1):
        sent = c.put(f"/documents/{doc}/uploads/{upload}/parts/{number}", content=part)
        assert sent.status_code == 200, sent.text
        assert sent.json()["bytes"] == len(part)
    return upload


def _shown(c, doc: str) -> set[str]:
    return ids_of(c.get(f"/documents/{doc}/viewport", params=ALL).json()["items"])


@pytest.mark.parametrize("encoding", ["identity", "gzip"])
def test_parts_cut_anywhere_import_as_one_body(data_dir, encoding):
    boxes, kinds = scenes.uniform(3000, seed=4)
    body = ndjson(boxes, kinds)
    sent = gzip.compress(body) if encoding == "gzip" else body
    with client() as c:
        doc = c.post("/documents", json={"name": "big"}).json()["id"]
        upload = _upload(c, doc, _cut(sent, 7), encoding=encoding)
        listed = c.get(f"/documents/{doc}/uploads/{upload}").json()
        assert [p["number"] for p in listed["parts"]] == list(range(1, 8))
        assert c.get(f"/documents/{doc}/viewport", params=ALL).json()["count"] == 0  # nothing yet
        committed = c.post(f"/documents/{doc}/uploads/{upload}/commit", json={"parts": 7})
        assert committed.status_code == 200, committed.text
        assert committed.json() == {"imported": 3000, "version": 1}
        assert _shown(c, doc) == expected(boxes, (-1e9, -1e9, 1e9, 1e9))
        rect = (1000.0, 1000.0, 9000.0, 7000.0)
        answer = c.get(
            f"/documents/{doc}/viewport", params=dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True))
        )
        assert ids_of(answer.json()["items"]) == expected(boxes, rect)
        assert c.get(f"/documents/{doc}/uploads/{upload}").status_code == 404  # gone once committed
        assert not list((data_dir / "uploads" / doc).iterdir())


def test_a_missing_part_refuses_the_commit_and_a_part_sent_again_replaces_itself(data_dir):
    boxes, kinds = scenes.uniform(500, seed=5)
    parts = _cut(ndjson(boxes, kinds), 3, seed=1)
    with client() as c:
        doc = c.post("/documents", json={"name": "d"}).json()["id"]
        upload = c.post(f"/documents/{doc}/uploads", json={}).json()["id"]
        base = f"/documents/{doc}/uploads/{upload}"
        for number in (1, 3):
            assert c.put(f"{base}/parts/{number}", content=parts[number - 1]).status_code == 200
        refused = c.post(f"{base}/commit", json={"parts": 3})
        assert refused.status_code == 409 and "parts 2 are missing" in refused.json()["detail"], refused.text
        past = c.post(f"{base}/commit", json={"parts": 2})
        assert past.status_code == 409 and "parts 3 were received past 2" in past.json()["detail"]
        assert c.get(f"/documents/{doc}").json()["version"] == 0  # nothing imported
        wrong = c.put(f"{base}/parts/2", content=b'{"id": "stray", "x0": 0, "y0": 0, "x1": 1, "y1": 1}\n')
        again = [c.put(f"{base}/parts/2", content=parts[1]) for _ in range(2)]  # replaces, twice
        assert wrong.status_code == 200 and [a.json() for a in again] == [again[0].json()] * 2
        assert again[0].json()["xxh3"] != wrong.json()["xxh3"]
        assert [p["bytes"] for p in c.get(base).json()["parts"]] == [len(p) for p in parts]
        assert c.post(f"{base}/commit", json={"parts": 3}).json() == {"imported": 500, "version": 1}
        assert _shown(c, doc) == expected(boxes, (-1e9, -1e9, 1e9, 1e9))  # no "stray"


def test_a_bad_line_is_named_nothing_is_imported_and_the_upload_stays_to_be_mended(data_dir):
    good = ndjson(*scenes.uniform(200, seed=6))
    bad = b'{"id": "x", "x0": 5, "y0": 0, "x1": 4, "y1": 1}\n'
    with client() as c:
        doc = c.post("/documents", json={"name": "d"}).json()["id"]
        c.post(f"/documents/{doc}/items", content=good, headers=NDJSON).raise_for_status()
        upload = _upload(c, doc, [good, bad], mode="replace")
        base = f"/documents/{doc}/uploads/{upload}"
        refused = c.post(f"{base}/commit", json={"parts": 2})
        assert refused.status_code == 422 and "line 201" in refused.json()["detail"], refused.text
        assert c.get(f"/documents/{doc}").json()["version"] == 1  # the document as it was
        c.put(f"{base}/parts/2", content=bad.replace(b'"x0": 5', b'"x0": 3')).raise_for_status()
        assert c.post(f"{base}/commit", json={"parts": 2}).json() == {"imported": 201, "version": 2}


def test_uploads_are_checked_as_writes_and_named_by_what_was_wrong(data_dir, monkeypatch):
    monkeypatch.setenv("VANTAGE_TOKENS", "secret")
    monkeypatch.setenv("VANTAGE_MAX_UPLOAD_BYTES", "1000")
    from app.config import get_settings

    get_settings.cache_clear()
    auth = {"authorization": "Bearer secret"}
    with client() as c:
        doc = c.post("/documents", json={"name": "d"}, headers=auth).json()["id"]
        assert c.post(f"/documents/{doc}/uploads", json={}).status_code == 401
        assert c.post(f"/documents/{doc}/uploads", json={"format": "xml"}, headers=auth).status_code == 422
        assert c.post("/documents/nope/uploads", json={}, headers=auth).status_code == 404
        upload = c.post(f"/documents/{doc}/uploads", json={}, headers=auth).json()["id"]
        base = f"/documents/{doc}/uploads/{upload}"
        assert c.put(f"{base}/parts/0", content=b"x", headers=auth).status_code == 422
        assert (
            c.put(f"/documents/{doc}/uploads/{'0' * 32}/parts/1", content=b"x", headers=auth).status_code
            == 404
        )
        assert (
            c.put(f"/documents/{doc}/uploads/..%2F..%2Fx/parts/1", content=b"x", headers=auth).status_code
            == 404
        )
        assert c.put(f"{base}/parts/1", content=b"x" * 600, headers=auth).status_code == 200
        full = c.put(f"{base}/parts/2", content=b"x" * 600, headers=auth)
        assert full.status_code == 413 and "VANTAGE_MAX_UPLOAD_BYTES" in full.json()["detail"]
        assert [p["number"] for p in c.get(base, headers=auth).json()["parts"]] == [1]  # nothing of it kept
        again = c.put(f"{base}/parts/1", content=b"y" * 600, headers=auth)  # replaces itself: room enough
        assert again.status_code == 200, again.text
        assert c.delete(base, headers=auth).status_code == 204
        assert c.get(base, headers=auth).status_code == 404
        assert c.delete(f"/documents/{doc}", headers=auth).status_code == 204
        assert not (data_dir / "uploads" / doc).exists()


def test_an_upload_commits_into_either_store_alike(tmp_path, database_url):
    """Parts kept by the server that received them, committed into the shared PostgreSQL store:
    a second server on that store answers the same."""
    boxes, kinds = scenes.uniform(2000, seed=9)
    env = {"VANTAGE_DATABASE_URL": database_url}
    first, url = launch(tmp_path / "one", env=env, output=subprocess.DEVNULL)
    second, other = launch(tmp_path / "two", env=env, output=subprocess.DEVNULL)
    try:
        with httpx.Client(base_url=url) as c, httpx.Client(base_url=other) as d:
            doc = c.post("/documents", json={"name": "d"}).json()["id"]
            upload = _upload(c, doc, _cut(gzip.compress(ndjson(boxes, kinds)), 5), encoding="gzip")
            committed = c.post(f"/documents/{doc}/uploads/{upload}/commit", json={"parts": 5})
            assert committed.json() == {"imported": 2000, "version": 1}, committed.text
            everything = expected(boxes, (-1e9, -1e9, 1e9, 1e9))
            assert _shown(c, doc) == everything
            answer = d.get(f"/documents/{doc}/viewport", params={**ALL, "min_version": 1})
            assert ids_of(answer.json()["items"]) == everything
    finally:
        stop(first)
        stop(second)


def test_a_server_killed_mid_upload_stores_nothing_and_keeps_the_parts_it_had(tmp_path):
    boxes, kinds = scenes.uniform(2000, seed=7)
    parts = _cut(ndjson(boxes, kinds), 4, seed=2)
    process, url = launch(tmp_path, output=subprocess.DEVNULL)
    try:
        with httpx.Client(base_url=url) as c:
            doc = c.post("/documents", json={"name": "d"}).json()["id"]
            upload = _upload(c, doc, parts[:2])
        # part 3 half sent when the server dies
        with httpx.Client(base_url=url) as c:

            def body():
                yield parts[2][: len(parts[2]) // 2]
                process.send_signal(signal.SIGKILL)
                process.wait()
                yield parts[2][len(parts[2]) // 2 :]

            with pytest.raises(httpx.TransportError):
                c.put(f"/documents/{doc}/uploads/{upload}/parts/3", content=body())
    finally:
        stop(process)
    process, url = launch(tmp_path, output=subprocess.DEVNULL)
    try:
        with httpx.Client(base_url=url) as c:
            assert c.get(f"/documents/{doc}").json()["version"] == 0
            listed = c.get(f"/documents/{doc}/uploads/{upload}").json()["parts"]
            assert [(p["number"], p["bytes"]) for p in listed] == [(1, len(parts[0])), (2, len(parts[1]))]
            for number in (3, 4):
                c.put(f"/documents/{doc}/uploads/{upload}/parts/{number}", content=parts[number - 1])
            committed = c.post(f"/documents/{doc}/uploads/{upload}/commit", json={"parts": 4})
            assert committed.json() == {"imported": 2000, "version": 1}, committed.text
            assert _shown(c, doc) == expected(boxes, (-1e9, -1e9, 1e9, 1e9))
    finally:
        stop(process)


def test_the_clients_send_a_big_import_as_an_upload_of_parts_without_being_asked(tmp_path):
    import asyncio

    from app.client import AsyncClient, Client

    boxes, kinds = scenes.uniform(3000, seed=8)
    path = tmp_path / "big.ndjson.gz"
    path.write_bytes(gzip.compress(ndjson(boxes, kinds)))
    everything = expected(boxes, (-1e9, -1e9, 1e9, 1e9))
    process, url = launch(tmp_path / "data", output=subprocess.DEVNULL)
    try:
        with Client(url, part_bytes=10_000) as c:
            sent = []
            c.http.event_hooks["request"].append(lambda r: sent.append((r.method, r.url.path.split("/")[3:])))
            doc = c.create_document("big")["id"]
            assert c.import_items(doc, path) == {"imported": 3000, "version": 1}  # a gzip file, in parts
            parts = [p for m, p in sent if m == "PUT"]
            assert len(parts) == -(-path.stat().st_size // 10_000) >= 3
            assert ids_of(c.viewport(doc, (-1e9, -1e9, 1e9, 1e9), limit=100_000)["items"]) == everything
            items = [{"id": f"n{k}", "x0": k, "y0": 0, "x1": k + 1, "y1": 1} for k in range(2000)]
            assert c.import_items(doc, items, replace=True) == {"imported": 2000, "version": 2}

            def failing():  # an iterable that fails after a few parts went
                yield from items[:1500]
                raise RuntimeError("the source broke")

            with pytest.raises(RuntimeError, match="the source broke"):
                c.import_items(doc, failing())
            assert c.describe(doc)["version"] == 2  # nothing stored
            assert not list((tmp_path / "data" / "uploads" / doc).iterdir())  # nothing left behind
            small = c.create_document("small")["id"]
            sent.clear()
            assert c.import_items(small, items[:10]) == {"imported": 10, "version": 1}
            assert [m for m, _ in sent] == ["POST"]  # under a part: one body, as before

        async def asynchronously() -> dict:
            async with AsyncClient(url, part_bytes=10_000) as a:
                return await a.import_items(doc, path, replace=True)

        assert asyncio.run(asynchronously()) == {"imported": 3000, "version": 3}
    finally:
        stop(process)


def test_an_upload_set_aside_by_a_killed_commit_is_put_back_at_start_up(tmp_path):
    from app.uploads import Uploads

    uploads = Uploads(tmp_path, 1 << 30)
    upload = uploads.new("doc1", "ndjson", "identity", "upsert")
    writer = uploads.writer(upload, 1)
    writer.write(b'{"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1}\n')
    writer.keep()
    claim = uploads.claim(upload, 1)
    ended = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    (tmp_path / "doc1" / f".{upload.id}.committing" / "owner").write_text(ended.stdout)  # its process died
    claim.body.close()
    with pytest.raises(NotFound):
        uploads.claim(upload, 1)  # set aside: not to be committed twice
    uploads.sweep()
    assert [p.number for p in uploads.parts(upload)] == [1]  # back, to commit again
    live = uploads.claim(upload, 1)  # a commit under way in a process that runs: left alone
    uploads.sweep()
    assert (tmp_path / "doc1" / f".{upload.id}.committing").exists()
    live.finish()
    assert not list((tmp_path / "doc1").iterdir())


def test_a_gzip_body_that_inflates_past_one_bodys_cap_goes_as_an_upload(tmp_path):
    from app.client import Client

    boxes = np.array([[k, 0, k + 1, 1] for k in range(3000)], float)
    text = {"text": "the same words, over and over; " * 8}  # compresses well
    body = b"".join(
        orjson.dumps({"id": f"i{k}", "x0": b[0], "y0": b[1], "x1": b[2], "y1": b[3], "data": text}) + b"\n"
        for k, b in enumerate(boxes.tolist())
    )
    assert len(gzip.compress(body)) < 100_000 < len(body)
    process, url = launch(tmp_path, env={"VANTAGE_MAX_BODY_BYTES": "100000"}, output=subprocess.DEVNULL)
    try:
        with Client(url) as c:
            doc = c.create_document("d")["id"]
            assert c.import_items(doc, body, gzip=True) == {"imported": 3000, "version": 1}
            assert ids_of(c.viewport(doc, (-1e9, -1e9, 1e9, 1e9), limit=100_000)["items"]) == expected(
                boxes, (-1e9, -1e9, 1e9, 1e9)
            )
    finally:
        stop(process)
