"""The HTTP service end to end through TestClient, every answer checked against brute force."""

import itertools
import math

import numpy as np
import oracle
import orjson
from service import NDJSON, client, expected, ids_of, ndjson

from spatial import scenes


def test_documents_are_created_listed_described_and_deleted(data_dir):
    with client() as c:
        created = c.post("/documents", json={"name": "a"})
        assert created.status_code == 201
        doc = created.json()
        assert doc["items"] == 0 and doc["version"] == 0 and doc["bounds"] is None
        assert [d["id"] for d in c.get("/documents").json()] == [doc["id"]]
        assert c.get(f"/documents/{doc['id']}").json()["name"] == "a"
        assert c.delete(f"/documents/{doc['id']}").status_code == 204
        missing = c.get(f"/documents/{doc['id']}")
        assert missing.status_code == 404 and doc["id"] in missing.json()["detail"]
        assert c.post("/documents", json={"name": ""}).status_code == 422


def test_viewport_answers_equal_brute_force(document):
    c, doc, boxes = document
    for rect in scenes.panning_path(boxes, 25, seed=2):
        x0, y0, x1, y1 = rect.tolist()
        body = c.get(f"/documents/{doc}/viewport", params={"x0": x0, "y0": y0, "x1": x1, "y1": y1}).json()
        assert body["truncated"] is False and body["version"] == 1
        assert ids_of(body["items"]) == expected(boxes, rect)
        assert body["count"] == len(body["items"])


def test_items_round_trip_with_every_digit(document):
    c, doc, boxes = document
    item = c.get(f"/documents/{doc}/items/i5").json()
    assert [item[k] for k in ("x0", "y0", "x1", "y1")] == boxes[5].tolist()
    assert item["kind"] == "page" and item["z"] == 5  # the first six items are the page frames


def test_diff_answers_equal_the_difference_of_two_viewports(document):
    c, doc, boxes = document
    path = scenes.panning_path(boxes, 25, seed=3)
    for old, new in itertools.pairwise(path):
        params = {"from": ",".join(map(repr, old.tolist())), "to": ",".join(map(repr, new.tolist()))}
        body = c.get(f"/documents/{doc}/diff", params=params).json()
        before, after = expected(boxes, old), expected(boxes, new)
        assert ids_of(body["enter"]) == after - before
        assert set(body["leave"]) == before - after


def test_level_of_detail_shows_big_items_and_aggregates_for_the_rest(document):
    c, doc, boxes = document
    rect = x0, y0, x1, y1 = boxes[:, 0].min(), boxes[:, 1].min(), boxes[:, 2].max(), boxes[:, 3].max()
    params = {"x0": x0, "y0": y0, "x1": x1, "y1": y1, "scale": 0.05, "min_px": 2}
    body = c.get(f"/documents/{doc}/viewport", params=params).json()
    size = 2.0 ** body["band"]
    assert size >= 2 / 0.05  # the band's items are at least min_px on screen
    ids = [f"i{i}" for i in range(len(boxes))]
    oracle.check_shown(boxes, ids, rect, size, body["items"])
    aggs = [e for e in body["items"] if "agg" in e]
    assert body["aggregates"] == len(aggs) > 0 and body["count"] == len(body["items"]) - len(aggs)
    assert body["omitted_small"] == len(boxes) - body["count"] == sum(a["agg"]["count"] for a in aggs)


def test_responses_over_the_limit_say_truncated(document):
    c, doc, boxes = document
    params = {"x0": -1e9, "y0": -1e9, "x1": 1e9, "y1": 1e9, "limit": 10}
    body = c.get(f"/documents/{doc}/viewport", params=params).json()
    assert body["truncated"] is True and len(body["items"]) == 10 and body["count"] == len(boxes)


def test_a_bad_line_stores_nothing_and_is_named(document):
    c, doc, boxes = document
    good = b'{"id": "new1", "x0": 0, "y0": 0, "x1": 1, "y1": 1}\n'
    cases = {
        b'{"id": "new2", "x0": 5, "y0": 0, "x1": 4, "y1": 1}': "line 2: x0=5.0 > x1=4.0; swap them",
        b'{"id": "new2", "x0": NaN, "y0": 0, "x1": 4, "y1": 1}': "line 2: JSON is malformed",
        b'{"id": "new2", "x0": 1e999, "y0": 0, "x1": 4, "y1": 1}': "line 2: Number out of range - at `$.x0`",
        b'{"id": "new2", "x0": 0, "y0": 0, "x1": 4}': "line 2: Object missing required field `y1`",
        b'{"id": "new2", "x0": "0", "y0": 0, "x1": 4, "y1": 1}': "line 2: Expected `float`, got `str` - at `$.x0`",
        b'{"id": "", "x0": 0, "y0": 0, "x1": 4, "y1": 1}': "line 2: Expected `str` of length >= 1 - at `$.id`",
        b'{"id": "new2", "x0": 0, "y0": 0, "x1": 4, "y1": 1, "z": true}': "line 2: Expected `int`, got `bool`",
        b'{"id": "new2", "x0": 0, "y0": 0, "x1": 4, "y1": 1, "colour": 1}': "unknown field `colour`",
        b'{"id": "new2", "x0": 0, "y0": 0, "x1": 4, "y1": 1, "data": {"t": "'
        + b"x" * 5000
        + b'"}}': "line 2: data is 5008 bytes as JSON; the limit is 4096",
        b"[1, 2]": "line 2: Expected `object`, got `array`",
        b'{"id": "a", "x0": 0, "y0": 0, "x1": 4, "y1": 1} {"id": "b", "x0": 0, "y0": 0, "x1": 4, "y1": 1}': "line 2: JSON is malformed",
        b"\n\n" + b'{"id": "new2"}': "line 4: Object missing required field `x0`",  # blank lines count
        b'{"id": "new2", "x0": 0, "y0": 0, "x1": 4, "y1": 1, "kind": "'
        + b"k" * 70000
        + b'"}': "line 2: longer than 65536 bytes, the limit (VANTAGE_MAX_LINE_BYTES)",
        b'{"id": "new2", "x0": 0, "y0": 0, "x1": 4, "y1": 1, "kind": "\xff"}': "line 2: not valid UTF-8 (byte 0xff at offset 60)",
        b'{"id": "new2", "x0": 0, "y0": 0, "x1": 4, "y1": 1, "data": {"a": '
        + b"[" * 1000
        + b"]" * 1000
        + b"}}": "line 2: nested too deeply",
        b'{"id": "new2", "x0": 0, "y0": 0, "x1": 4, "y1": 1, "data": {"a": '
        + b"[" * 40
        + b"]" * 40
        + b"}}": "line 2: data is nested 41 levels deep; the limit is 32",
    }
    for bad, message in cases.items():
        answer = c.post(f"/documents/{doc}/items", content=good + bad + b"\n", headers=NDJSON)
        assert answer.status_code == 422 and message in answer.json()["detail"], answer.text
    described = c.get(f"/documents/{doc}").json()
    assert described["items"] == len(boxes) and described["version"] == 1
    assert c.get(f"/documents/{doc}/items/new1").status_code == 404


def test_bad_viewports_are_refused_with_the_reason(document):
    c, doc, _ = document
    inverted = c.get(f"/documents/{doc}/viewport", params={"x0": 5, "y0": 0, "x1": 4, "y1": 1})
    assert inverted.status_code == 422 and "x0=5.0 > x1=4.0" in inverted.json()["detail"]
    infinite = c.get(f"/documents/{doc}/viewport", params={"x0": 0, "y0": 0, "x1": "inf", "y1": 1})
    assert infinite.status_code == 422 and "finite" in infinite.json()["detail"]
    garbled = c.get(f"/documents/{doc}/diff", params={"from": "0,0,1", "to": "0,0,1,1"})
    assert garbled.status_code == 422 and "from must be four numbers" in garbled.json()["detail"]
    assert c.get("/documents/nope/viewport", params={"x0": 0, "y0": 0, "x1": 1, "y1": 1}).status_code == 404


def test_single_item_edits_show_in_the_next_query(document):
    c, doc, boxes = document
    far = {"x0": 1e6, "y0": 1e6, "x1": 1e6 + 10, "y1": 1e6 + 10, "kind": "note"}
    assert c.put(f"/documents/{doc}/items/fresh", json=far).status_code == 201
    moved = c.put(f"/documents/{doc}/items/i3", json=far)
    assert moved.status_code == 200 and moved.json()["version"] == 3
    near = c.get(f"/documents/{doc}/viewport", params={"x0": 1e6, "y0": 1e6, "x1": 1e6, "y1": 1e6}).json()
    assert ids_of(near["items"]) == {"fresh", "i3"} and near["version"] == 3
    assert c.delete(f"/documents/{doc}/items/fresh").json()["version"] == 4
    assert c.delete(f"/documents/{doc}/items/fresh").status_code == 404
    assert c.put(f"/documents/{doc}/items/x", json={**far, "x1": math.pi}).status_code == 422
    assert c.put(f"/documents/{doc}/items/x", json={**far, "id": "y"}).status_code == 422
    assert c.get(f"/documents/{doc}").json()["items"] == len(boxes)


def test_everything_survives_a_restart(document, data_dir):
    c, doc, _boxes = document
    c.put(f"/documents/{doc}/items/i0", json={"x0": -50, "y0": -50, "x1": -40, "y1": -40})
    rect = {"x0": -60, "y0": -60, "x1": 700, "y1": 900}
    before = c.get(f"/documents/{doc}/viewport", params=rect).json()
    with client() as again:  # a new app start-up: the index is rebuilt from the store
        after = again.get(f"/documents/{doc}/viewport", params=rect).json()
    assert ids_of(after["items"]) == ids_of(before["items"]) and after["version"] == before["version"]
    assert sorted(map(orjson.dumps, after["items"])) == sorted(map(orjson.dumps, before["items"]))


def test_readers_during_an_import_see_the_old_or_the_new_version_never_a_mix(document):
    import threading

    c, doc, boxes = document
    moved = boxes + 100.0  # the import moves every item: any mix of versions would show
    rect = (0.0, 0.0, 700.0, 2000.0)
    answers = {1: expected(boxes, rect), 2: expected(moved, rect)}
    seen, done = [], threading.Event()

    def read() -> None:
        params = dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True))
        while not done.is_set():
            body = c.get(f"/documents/{doc}/viewport", params=params).json()
            seen.append((body["version"], ids_of(body["items"])))

    reader = threading.Thread(target=read)
    reader.start()
    try:
        assert c.post(f"/documents/{doc}/items", content=ndjson(moved), headers=NDJSON).json()["version"] == 2
    finally:
        done.set()
        reader.join()
    read_once = c.get(
        f"/documents/{doc}/viewport", params=dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True))
    ).json()
    seen.append((read_once["version"], ids_of(read_once["items"])))
    assert seen and all(ids == answers[version] for version, ids in seen)
    assert seen[-1][0] == 2


def test_every_route_is_documented_with_examples(document):
    c, _, _ = document
    schema = c.get("/openapi.json").json()
    operations = [(path, method, op) for path, ops in schema["paths"].items() for method, op in ops.items()]
    assert len(operations) == 23  # and the WebSocket stream, described in the API description
    for path, method, op in operations:
        assert op.get("description"), f"{method} {path} has no description"
        ok = next(code for code in op["responses"] if code.startswith("2"))
        if ok != "204":  # JSON, or NDJSON for the export: each with its example
            contents = op["responses"][ok]["content"]
            assert contents and all("example" in c for c in contents.values()), f"{method} {path}"
        for param in op.get("parameters", []):
            if param["in"] == "query" and param["required"]:
                assert param["schema"].get("examples") or param.get("examples"), (
                    f"{method} {path} {param['name']}"
                )
        for content in op.get("requestBody", {}).get("content", {}).values():  # each type it takes
            assert "example" in content or "examples" in content["schema"] or "$ref" in content["schema"], (
                path
            )
    assert "/stream" in schema["info"]["description"] and c.get("/docs").status_code == 200


def test_an_oversized_body_is_refused_and_stores_nothing(document, monkeypatch):
    _, doc, boxes = document
    monkeypatch.setenv("VANTAGE_MAX_BODY_BYTES", "1000")
    monkeypatch.setenv("VANTAGE_MAX_JSON_BYTES", "1000")
    with client() as c:
        answer = c.post(f"/documents/{doc}/items", content=ndjson(boxes[:100]), headers=NDJSON)
        assert answer.status_code == 413, answer.text
        assert (
            answer.json()["detail"]
            == "the body exceeds 1000 bytes, the most this route takes (VANTAGE_MAX_BODY_BYTES)"
        )
        item = {"x0": 0, "y0": 0, "x1": 1, "y1": 1, "data": {"text": "x" * 3000}}  # under MAX_DATA_BYTES
        put = c.put(f"/documents/{doc}/items/big", json=item)
        assert put.status_code == 413 and "VANTAGE_MAX_JSON_BYTES" in put.json()["detail"], put.text
        assert c.get(f"/documents/{doc}").json()["version"] == 1


def test_cells_cover_every_item_in_the_viewport(document):
    c, doc, boxes = document
    rect = (0.0, 500.0, 700.0, 1500.0)
    body = c.get(
        f"/documents/{doc}/cells", params=dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True))
    ).json()
    cells = body["cells"]
    assert cells[0]["depth"] == 0 and [cell["depth"] for cell in cells] == sorted(
        cell["depth"] for cell in cells
    )
    leaves = np.array([cell["box"] for cell in cells if cell["leaf"]])
    assert all(oracle.hits(np.array([cell["box"]]), rect)[0] for cell in cells)
    for i in np.flatnonzero(oracle.hits(boxes, rect)):  # each shown item lies inside a leaf drawn
        x0, y0, x1, y1 = boxes[i]
        inside = (leaves[:, 0] <= x0) & (leaves[:, 1] <= y0) & (leaves[:, 2] >= x1) & (leaves[:, 3] >= y1)
        assert inside.any()
    assert (
        len(
            c.get(
                f"/documents/{doc}/cells",
                params={**dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)), "limit": 3},
            ).json()["cells"]
        )
        == 3
    )


def test_a_scale_so_small_no_item_is_big_enough_shows_aggregates_of_everything(document):
    c, doc, boxes = document
    params = {"x0": -1e300, "y0": -1e300, "x1": 1e300, "y1": 1e300, "scale": 1e-308, "min_px": 1e72}
    body = c.get(f"/documents/{doc}/viewport", params=params).json()
    assert body["count"] == 0 and body["omitted_small"] == len(boxes)
    assert all("agg" in e for e in body["items"])
    assert sum(e["agg"]["count"] for e in body["items"]) == len(boxes)


def test_two_imports_into_one_document_serialise(document):
    import threading

    c, doc, boxes = document
    moves = {10.0: None, 20.0: None}

    def move(dx: float) -> None:
        moves[dx] = c.post(f"/documents/{doc}/items", content=ndjson(boxes + dx), headers=NDJSON).json()[
            "version"
        ]

    threads = [threading.Thread(target=move, args=(dx,)) for dx in moves]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(moves.values()) == [2, 3]  # one after the other, never the same version
    last = max(moves, key=moves.get)
    rect = (0.0, 0.0, 700.0, 2000.0)
    shown = c.get(
        f"/documents/{doc}/viewport", params=dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True))
    ).json()
    assert shown["version"] == 3 and ids_of(shown["items"]) == expected(boxes + last, rect)
    assert all(item["x0"] == boxes[int(item["id"][1:]), 0] + last for item in shown["items"])


def test_a_diff_over_its_limit_says_truncated_and_how_many_entered(document):
    c, doc, boxes = document
    old, new = (0.0, 0.0, 700.0, 100.0), (0.0, 0.0, 700.0, 1800.0)  # zooming out: nothing leaves
    params = {"from": ",".join(map(str, old)), "to": ",".join(map(str, new)), "limit": 5}
    body = c.get(f"/documents/{doc}/diff", params=params).json()
    entering = expected(boxes, new) - expected(boxes, old)
    assert len(entering) > 5 and body["truncated"] is True and body["entered"] == len(entering)
    assert body["reset"] is False and body["leave"] == []
    assert len(body["enter"]) == 5 and ids_of(body["enter"]) <= entering
    whole = c.get(f"/documents/{doc}/diff", params={**params, "limit": len(entering)}).json()
    assert whole["truncated"] is False and ids_of(whole["enter"]) == entering


def test_answers_are_compressed_for_clients_that_accept_it(document):
    c, doc, _ = document
    params = {"x0": 0, "y0": 0, "x1": 1920, "y1": 1080}
    plain = c.get(f"/documents/{doc}/viewport", params=params, headers={"accept-encoding": "identity"})
    packed = c.get(f"/documents/{doc}/viewport", params=params, headers={"accept-encoding": "gzip"})
    assert "content-encoding" not in plain.headers and packed.headers["content-encoding"] == "gzip"
    assert packed.json() == plain.json()  # the client inflates it: the same answer
    assert int(packed.headers["content-length"]) < len(plain.content) / 3
    small = c.get(f"/documents/{doc}", headers={"accept-encoding": "gzip"})
    assert "content-encoding" not in small.headers  # under a kilobyte: as it is
