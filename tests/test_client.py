"""The Python client (app/client/) against a real server process: every route round-trips,
errors carry the server's status and detail, the stream holds what brute force shows."""

import asyncio
import gzip
import itertools
import json

import httpx
import numpy as np
import oracle
import pytest
from service import expected

from app.client import AsyncClient, Client, Stream, VantageError
from app.demo import ndjson_lines
from app.launch import launch
from spatial import scenes

SCREEN = (0.0, 0.0, 700.0, 900.0)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """One server for the module (a start is ~2 s): each test makes documents of its own."""
    process, url = launch(tmp_path_factory.mktemp("client-data"))
    try:
        yield url
    finally:
        process.terminate()
        process.communicate(timeout=15)


@pytest.fixture
def report():
    """A three-page generated report: ``(boxes, NDJSON lines)``."""
    boxes, kinds = scenes.long_document(pages=3, seed=4)
    return boxes, list(ndjson_lines(boxes, kinds))


def _normal(item: dict) -> dict:
    """An item as the server answers it: the defaults filled in."""
    return {"kind": "box", "z": 0, **item}


def _by_id(items) -> dict[str, dict]:
    return {item["id"]: _normal(item) for item in items}


def _ids(items) -> set[str]:
    return {item["id"] for item in items}


def _pans(boxes: np.ndarray, count: int = 6) -> list[tuple]:
    return [tuple(r) for r in scenes.panning_path(boxes, count, seed=9).tolist()]


def test_documents_import_and_export_round_trip(server, report, tmp_path):
    boxes, lines = report
    sent = _by_id(json.loads(line) for line in lines)
    path = tmp_path / "report.ndjson"
    path.write_bytes(b"".join(lines))
    zipped = tmp_path / "report.ndjson.gz"
    zipped.write_bytes(gzip.compress(b"".join(lines)))
    array = tmp_path / "report.json"
    array.write_text(json.dumps([json.loads(line) for line in lines]))
    with Client(server) as vantage:
        assert vantage.health() == {"status": "ok", "store": "sqlite", "reachable": True}
        before = {d["id"] for d in vantage.documents()}  # the other tests' documents
        made = [vantage.create_document(name)["id"] for name in ("file", "iterator", "gz", "array")]
        assert {d["id"] for d in vantage.documents()} == before | set(made) and not before & set(made)
        file_doc, iter_doc, gz_doc, array_doc = made
        assert vantage.import_items(file_doc, path, gzip=True) == {"imported": len(boxes), "version": 1}
        dicts = (json.loads(line) for line in lines)  # a generator: streamed, never a list
        assert vantage.import_items(iter_doc, dicts)["imported"] == len(boxes)
        assert vantage.import_items(gz_doc, zipped)["imported"] == len(boxes)  # sent gzip'd as it is
        assert vantage.import_items(array_doc, array)["imported"] == len(boxes)  # a JSON array
        for doc in made:
            assert _by_id(vantage.export(doc)) == sent
            assert vantage.describe(doc)["items"] == len(boxes)
        # Lines (str) replace what the document held; bytes bodies still go as they are.
        assert vantage.import_items(
            iter_doc, (line.decode().strip() for line in lines[:5]), replace=True
        ) == {
            "imported": 5,
            "version": 2,
        }
        assert _ids(vantage.export(iter_doc)) == {f"i{i}" for i in range(5)}
        assert vantage.import_items(iter_doc, b"".join(lines[5:10]))["imported"] == 5
        assert vantage.import_stream(iter_doc, iter(lines[10:20]), gzip=True)["imported"] == 10
        assert len(list(vantage.export_lines(iter_doc))) == 20
        vantage.delete_document(array_doc)
        assert array_doc not in {d["id"] for d in vantage.documents()}
        stats = vantage.stats()
        assert isinstance(stats, dict) and stats


def test_viewport_diff_and_cells_match_brute_force(server, report):
    boxes, lines = report
    ids = [f"i{i}" for i in range(len(boxes))]
    with Client(server) as vantage:
        doc = vantage.create_document("report")["id"]
        vantage.import_items(doc, iter(lines))
        pans = _pans(boxes)
        for rect in pans:
            assert _ids(vantage.viewport(doc, rect)["items"]) == expected(boxes, rect)
            body = vantage.viewport(doc, rect, scale=0.05, min_px=2)
            oracle.check_shown(boxes, ids, rect, 2.0 ** body["band"], body["items"])
        for old, new in itertools.pairwise(pans):
            body = vantage.diff(doc, old, new)
            assert _ids(body["enter"]) == expected(boxes, new) - expected(boxes, old)
            assert set(body["leave"]) == expected(boxes, old) - expected(boxes, new)
        cells = vantage.cells(doc, pans[0], limit=50)
        assert 0 < len(cells["cells"]) <= 50 and cells["version"] == 1


def test_edits_search_and_diff_since(server, report):
    boxes, lines = report
    with Client(server) as vantage:
        doc = vantage.create_document("report")["id"]
        version = vantage.import_items(doc, iter(lines))["version"]
        rect = SCREEN
        inside = sorted(expected(boxes, rect))
        moved, dropped, gone = inside[0], inside[1], inside[2:4]
        word = {
            "id": "w/1",
            "x0": 10,
            "y0": 10,
            "x1": 60,
            "y1": 20,
            "kind": "text",
            "data": {"text": "Hello there"},
        }
        assert vantage.put_item(doc, word) == {"id": "w/1", "version": version + 1}
        assert vantage.get_item(doc, "w/1") == {
            **word,
            "x0": 10.0,
            "y0": 10.0,
            "x1": 60.0,
            "y1": 20.0,
            "z": 0,
        }
        assert vantage.patch_item(doc, moved, {"x0": 5000, "x1": 5001})["version"] == version + 2
        assert vantage.get_item(doc, moved)["x1"] == 5001.0
        assert vantage.delete_item(doc, dropped) == {"id": dropped, "version": version + 3}
        assert vantage.delete_items(doc, gone) == {"deleted": 2, "version": version + 4}
        body = vantage.diff(doc, rect, rect, since=version)
        assert body["version"] == version + 4 and not body["reset"]
        assert _ids(body["enter"]) == {"w/1"}
        assert set(body["leave"]) == {moved, dropped, *gone}
        found = vantage.search(doc, "hello", limit=5)
        assert found["count"] == 1 and found["items"][0]["id"] == "w/1"
        assert vantage.search(doc, "nothing like it")["items"] == []
        assert vantage.supports_replace()


def test_errors_carry_status_and_detail(server, report):
    _, lines = report
    with Client(server) as vantage:
        with pytest.raises(VantageError) as caught:
            vantage.describe("nosuchdoc")
        assert caught.value.status == 404 and "nosuchdoc" in caught.value.detail
        assert isinstance(caught.value, httpx.HTTPStatusError)  # what earlier callers catch
        doc = vantage.create_document("report")["id"]
        bad = [lines[0], b'{"id": "b", "x0": 5, "y0": 0, "x1": 4, "y1": 1}\n']
        with pytest.raises(VantageError) as caught:
            vantage.import_items(doc, iter(bad))
        assert caught.value.status == 422 and "line 2" in caught.value.detail
        assert vantage.describe(doc)["items"] == 0  # all or nothing
        with pytest.raises(VantageError) as caught:
            vantage.diff(doc, SCREEN, SCREEN, since=99)
        assert caught.value.status == 409 and "99" in caught.value.detail
        with pytest.raises(VantageError) as caught:
            vantage.get_item(doc, "w1")
        assert caught.value.status == 404
        with pytest.raises(VantageError) as caught:
            vantage.viewport(doc, (10, 0, 0, 10))
        assert caught.value.status == 422 and caught.value.detail
        with pytest.raises(VantageError) as caught:
            Stream(server, "nosuchdoc").view(SCREEN)
        assert caught.value.status == 404 and "nosuchdoc" in caught.value.detail
        with vantage.stream(doc) as stream, pytest.raises(VantageError) as caught:
            stream.view((10, 0, 0, 10))
        assert caught.value.status == 422


def test_stream_holds_what_brute_force_shows_and_gets_edits(server, report):
    boxes, lines = report
    ids = [f"i{i}" for i in range(len(boxes))]
    with Client(server) as vantage:
        doc = vantage.create_document("report")["id"]
        vantage.import_items(doc, iter(lines))
        with vantage.stream(doc) as stream:  # exact: every item touching the view
            for rect in _pans(boxes):
                answer = stream.view(rect)
                assert answer["type"] == "view" and answer["seq"] == stream.seq
                assert set(stream.items) == expected(boxes, rect)
            shown = sorted(stream.items)[0]
            item = stream.items[shown]
            version = vantage.patch_item(doc, shown, {"x1": item["x1"] + 1})["version"]
            pushed = stream.receive(timeout=30)
            assert pushed is not None and pushed["type"] == "edit"
            assert stream.items[shown]["x1"] == item["x1"] + 1 and stream.version == version
        with vantage.stream(doc, min_version=version) as stream:  # at that version or later
            assert stream.view(_pans(boxes)[0])["version"] >= version
        with pytest.raises(VantageError) as never, vantage.stream(doc, min_version=version + 9) as stream:
            stream.view(_pans(boxes)[0])
        assert never.value.status == 409 and "min_version" in str(never.value.detail)
        assert vantage.viewport(doc, _pans(boxes)[0], min_version=version)["version"] >= version
        with vantage.stream(doc, scale=0.05, min_px=2) as stream:  # at a level of detail
            for rect in _pans(boxes, 4):
                answer = stream.view(rect)
                assert stream.band == answer["band"]
                box = boxes.copy()
                box[int(shown[1:]), 2] += 1
                oracle.check_shown(box, ids, rect, 2.0 ** answer["band"], list(stream.items.values()))


def test_token_goes_in_the_header_and_the_stream_url(data_dir, report):
    _, lines = report
    process, url = launch(data_dir, env={"VANTAGE_TOKENS": "s3cret", "VANTAGE_READ_TOKEN": "true"})
    try:
        with Client(url) as anonymous, pytest.raises(VantageError) as caught:
            anonymous.documents()
        assert caught.value.status == 401
        with Client(url, token="wrong") as wrong, pytest.raises(VantageError) as caught:
            wrong.create_document("x")
        assert caught.value.status == 403
        with Client(url, token="s3cret") as vantage:
            doc = vantage.create_document("report")["id"]
            vantage.import_items(doc, iter(lines))
            with vantage.stream(doc) as stream:
                stream.view(SCREEN)
                assert stream.items
            with pytest.raises(VantageError) as caught:
                Stream(url, doc, "wrong").view(SCREEN)
            assert caught.value.status == 403
    finally:
        process.terminate()
        process.communicate(timeout=15)


def test_async_client_does_the_same(server, report, tmp_path):
    boxes, lines = report
    path = tmp_path / "report.ndjson"
    path.write_bytes(b"".join(lines))

    async def lines_coming():
        for line in lines:
            yield line

    async def main() -> None:
        async with AsyncClient(server) as vantage:
            assert (await vantage.health())["status"] == "ok"
            doc = (await vantage.create_document("report"))["id"]
            other = (await vantage.create_document("other"))["id"]
            assert (await vantage.import_items(doc, path, gzip=True))["imported"] == len(boxes)
            assert (await vantage.import_items(other, lines_coming()))["imported"] == len(boxes)
            assert (await vantage.import_items(other, iter(lines), replace=True))["version"] == 2
            exported = [item async for item in vantage.export(doc)]
            assert _by_id(exported) == _by_id(json.loads(line) for line in lines)
            rect = SCREEN
            assert _ids((await vantage.viewport(doc, rect))["items"]) == expected(boxes, rect)
            shown = sorted(expected(boxes, rect))[0]
            with pytest.raises(VantageError) as caught:
                await vantage.describe("nosuchdoc")
            assert caught.value.status == 404
            async with vantage.stream(doc) as stream:
                for rect in _pans(boxes):
                    await stream.view(rect)
                    assert set(stream.items) == expected(boxes, rect)
                await stream.view(SCREEN)
                version = (await vantage.delete_item(doc, shown))["version"]
                pushed = await stream.receive(timeout=30)
                assert pushed["type"] == "edit" and pushed["leave"] == [shown]
                assert shown not in stream.items and stream.version == version
            body = await vantage.diff(doc, SCREEN, SCREEN, since=version - 1)
            assert body["leave"] == [shown]
            assert (await vantage.delete_items(other, ["i1", "i2"]))["deleted"] == 2

    asyncio.run(main())


def test_every_async_route_answers_as_the_sync_one_does(server, report):
    """The two clients' methods, written once each, send the same requests: the same answers."""
    _, lines = report
    word = {"id": "w/1", "x0": 10, "y0": 10, "x1": 60, "y1": 20, "kind": "text", "data": {"text": "Hi"}}

    def answers(vantage, doc: str) -> list:
        return [
            vantage.describe(doc),
            vantage.put_item(doc, word),
            vantage.get_item(doc, "w/1"),
            vantage.patch_item(doc, "w/1", {"x1": 70}),
            vantage.viewport(doc, SCREEN, scale=0.5, min_px=1, limit=50),
            vantage.diff(doc, SCREEN, (0, 60, 700, 960), since=1),
            vantage.search(doc, "hi"),
            vantage.cells(doc, SCREEN, limit=20),
            vantage.delete_item(doc, "w/1"),
            vantage.delete_items(doc, [json.loads(lines[0])["id"]]),
            vantage.supports_replace(),
        ]

    async def answers_async(vantage, doc: str) -> list:
        return [
            await vantage.describe(doc),
            await vantage.put_item(doc, word),
            await vantage.get_item(doc, "w/1"),
            await vantage.patch_item(doc, "w/1", {"x1": 70}),
            await vantage.viewport(doc, SCREEN, scale=0.5, min_px=1, limit=50),
            await vantage.diff(doc, SCREEN, (0, 60, 700, 960), since=1),
            await vantage.search(doc, "hi"),
            await vantage.cells(doc, SCREEN, limit=20),
            await vantage.delete_item(doc, "w/1"),
            await vantage.delete_items(doc, [json.loads(lines[0])["id"]]),
            await vantage.supports_replace(),
        ]

    def without_ids(answer):  # the two documents' own ids and names aside
        return (
            {k: v for k, v in answer.items() if k not in {"id", "name", "created"}}
            if isinstance(answer, dict)
            else answer
        )

    with Client(server) as vantage:
        doc = vantage.create_document("sync")["id"]
        assert vantage.import_stream(doc, iter(lines), gzip=True)["imported"] == len(lines)
        expected_answers = answers(vantage, doc)
        exported = list(vantage.export_lines(doc))
        stats = vantage.stats()

    async def main() -> None:
        async with AsyncClient(server) as vantage:
            assert (await vantage.stats()).keys() == stats.keys()
            doc = (await vantage.create_document("async"))["id"]
            assert (await vantage.import_stream(doc, iter(lines), gzip=True))["imported"] == len(lines)
            got = await answers_async(vantage, doc)
            assert [without_ids(a) for a in got] == [without_ids(a) for a in expected_answers]
            assert [line async for line in vantage.export_lines(doc)] == exported
            assert doc in {d["id"] for d in await vantage.documents()}
            assert await vantage.delete_document(doc) is None
            assert doc not in {d["id"] for d in await vantage.documents()}

    asyncio.run(main())
