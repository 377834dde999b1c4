"""The item API people expect: PATCH changes some fields and keeps the rest, PUT replaces,
GET .../items exports NDJSON that an import takes back as it was, DELETE .../items deletes
many all or nothing, and an import with mode=replace replaces."""

import msgspec
import numpy as np
from service import NDJSON, ndjson

from app.registry import Registry

ITEM = {"x0": 1.0, "y0": 2.0, "x1": 3.0, "y1": 4.0, "kind": "note", "z": 5, "data": {"text": "hi"}}


def _export(c, doc: str) -> dict[str, dict]:
    answer = c.get(f"/documents/{doc}/items")
    assert answer.status_code == 200 and answer.headers["content-type"].startswith(NDJSON["content-type"])
    items = [msgspec.json.decode(line) for line in answer.content.splitlines()]
    assert answer.headers["vantage-version"] == str(c.get(f"/documents/{doc}").json()["version"])
    return {item["id"]: item for item in items}


def test_patch_changes_the_fields_given_and_keeps_the_rest(document):
    c, doc, _ = document
    assert c.put(f"/documents/{doc}/items/n1", json=ITEM).status_code == 201
    moved = c.patch(f"/documents/{doc}/items/n1", json={"x0": 0.5, "x1": 9.0})
    assert moved.status_code == 200 and moved.json()["version"] == 3
    assert c.get(f"/documents/{doc}/items/n1").json() == {"id": "n1", **ITEM, "x0": 0.5, "x1": 9.0}
    c.patch(f"/documents/{doc}/items/n1", json={"data": None, "kind": "text"})
    kept = {k: v for k, v in ITEM.items() if k != "data"} | {"x0": 0.5, "x1": 9.0, "kind": "text"}
    assert c.get(f"/documents/{doc}/items/n1").json() == {"id": "n1", **kept}  # data: null drops it


def test_a_bad_patch_is_refused_and_changes_nothing(document):
    c, doc, _ = document
    c.put(f"/documents/{doc}/items/n1", json=ITEM)
    cases = [
        ({"x0": 7.0}, 422, "x0=7.0 > x1=3.0"),  # the merged item is checked like any other
        ({"z": "top"}, 422, "Expected `int`"),
        ({"id": "other"}, 422, "does not match"),
        ([1, 2], 422, "JSON object"),
    ]
    for body, status, says in cases:
        answer = c.patch(f"/documents/{doc}/items/n1", json=body)
        assert (answer.status_code, says in answer.json()["detail"]) == (status, True), answer.text
    assert c.patch(f"/documents/{doc}/items/absent", json={"z": 1}).status_code == 404
    assert (
        c.patch(
            f"/documents/{doc}/items/n1", content=b"{}", headers={"content-type": "text/plain"}
        ).status_code
        == 415
    )
    assert c.get(f"/documents/{doc}/items/n1").json() == {"id": "n1", **ITEM}
    assert c.get(f"/documents/{doc}").json()["version"] == 2


def test_the_export_is_every_item_and_an_import_takes_it_back_as_it_was(document):
    c, doc, boxes = document
    c.put(f"/documents/{doc}/items/added", json=ITEM)
    c.patch(f"/documents/{doc}/items/i3", json={"kind": "image"})
    c.delete(f"/documents/{doc}/items/i4")
    exported = _export(c, doc)
    assert (
        len(exported) == len(boxes) and "i4" not in exported and exported["added"] == {"id": "added", **ITEM}
    )
    assert exported["i3"]["kind"] == "image" and exported["i7"]["x0"] == boxes[7, 0]
    copy = c.post("/documents", json={"name": "copy"}).json()["id"]
    body = c.get(f"/documents/{doc}/items").content
    assert c.post(f"/documents/{copy}/items", content=body, headers=NDJSON).json()["imported"] == len(boxes)
    assert _export(c, copy) == exported


def test_many_items_are_deleted_at_once_all_or_nothing(document):
    c, doc, boxes = document
    gone = c.request("DELETE", f"/documents/{doc}/items", json={"ids": ["i1", "i2", "i2", "i9"]})
    assert gone.status_code == 200 and gone.json() == {"deleted": 3, "version": 2}
    row = c.app.state.registry.store.document(doc)  # what listing shows once the document closes
    assert (row["version"], row["items"]) == (2, len(boxes) - 3)
    registry = c.app.state.registry
    reopened = Registry(registry.store, registry.files, 1 << 30)[doc].snapshot  # as a restart reads it
    assert {reopened.position(i) for i in ("i1", "i2", "i9")} == {None} and len(reopened.tree) == len(
        boxes
    ) - 3
    assert not {"i1", "i2", "i9"} & set(_export(c, doc))
    refused = c.request("DELETE", f"/documents/{doc}/items", json={"ids": ["i10", "nope", "i1"]})
    assert refused.status_code == 404 and "'nope', 'i1'" in refused.json()["detail"]
    assert "i10" in _export(c, doc) and c.get(f"/documents/{doc}").json()["version"] == 2
    assert c.request("DELETE", f"/documents/{doc}/items", json={"ids": []}).status_code == 422


def test_an_import_with_mode_replace_replaces_what_the_document_held(document):
    c, doc, _ = document
    fresh = np.array([[0.0, 0.0, 1.0, 1.0], [5.0, 5.0, 6.0, 6.0]])
    answer = c.post(
        f"/documents/{doc}/items", params={"mode": "replace"}, content=ndjson(fresh), headers=NDJSON
    )
    assert answer.json() == {"imported": 2, "version": 2}
    assert set(_export(c, doc)) == {"i0", "i1"} and c.get(f"/documents/{doc}").json()["items"] == 2
    bad = c.post(f"/documents/{doc}/items", params={"mode": "merge"}, content=ndjson(fresh), headers=NDJSON)
    assert bad.status_code == 422


def test_an_import_takes_a_json_array_and_gzip_too(document):
    import gzip

    c, doc, boxes = document
    items = [
        {"id": f"a{k}", "x0": float(k), "y0": 0.0, "x1": k + 1.0, "y1": 1.0, "kind": "note"} for k in range(3)
    ]
    answer = c.post(f"/documents/{doc}/items", json=items)
    assert answer.status_code == 200 and answer.json() == {"imported": 3, "version": 2}
    assert _export(c, doc)["a2"] == {**items[2], "z": 0}
    bad = c.post(f"/documents/{doc}/items", json=[*items, {"id": "b", "x0": 1, "y0": 0, "x1": 0, "y1": 1}])
    assert bad.status_code == 422 and bad.json()["detail"].startswith("item 3: x0=1.0 > x1=0.0"), bad.text
    assert c.post(f"/documents/{doc}/items", json={"id": "x"}).status_code == 422  # an object, not an array
    packed = gzip.compress(ndjson(boxes[:10] + 5000.0))
    headers = {**NDJSON, "content-encoding": "gzip"}
    assert c.post(f"/documents/{doc}/items", content=packed, headers=headers).json()["version"] == 3
    not_gzip = c.post(f"/documents/{doc}/items", content=b"plain", headers=headers)
    assert not_gzip.status_code == 422 and "is not gzip" in not_gzip.json()["detail"]
    other = c.post(f"/documents/{doc}/items", content=packed, headers={**NDJSON, "content-encoding": "br"})
    assert other.status_code == 415 and c.get(f"/documents/{doc}").json()["version"] == 3


def test_a_gzip_bomb_is_refused_at_the_limit(data_dir, monkeypatch):
    import gzip

    from service import client

    monkeypatch.setenv("VANTAGE_MAX_BODY_BYTES", "100000")
    with client() as c:
        doc = c.post("/documents", json={"name": "d"}).json()["id"]
        bomb = gzip.compress(b"\n" * 10_000_000)  # 10 MB of blank lines in ~10 kB
        answer = c.post(
            f"/documents/{doc}/items", content=bomb, headers={**NDJSON, "content-encoding": "gzip"}
        )
        assert answer.status_code == 413 and "inflates past 100000 bytes" in answer.json()["detail"]
        assert c.get(f"/documents/{doc}").json()["version"] == 0
