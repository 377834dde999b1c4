"""Search: the items whose text holds every word of a query, any case, in document order,
against brute force over the texts; edits show at once; what is not text never matches."""

import random

import pytest
from service import NDJSON

TEXTS = [
    "Quarterly revenue",
    "revenue forecast",
    "École de Paris",
    'a "quoted" word',
    "back\\slash",
    "ÉCOLE",
    "x",
]


def _import(c, doc, texts: list[str]) -> None:
    import orjson

    lines = [
        orjson.dumps(
            {"id": f"w{k}", "x0": k, "y0": 0, "x1": k + 1, "y1": 1, "kind": "text", "data": {"text": t}}
        )
        for k, t in enumerate(texts)
    ]
    lines.append(orjson.dumps({"id": "revenue-id", "x0": 0, "y0": 0, "x1": 1, "y1": 1, "kind": "revenue"}))
    assert c.post(f"/documents/{doc}/items", content=b"\n".join(lines), headers=NDJSON).status_code == 200


def _search(c, doc, q: str, limit: int = 1000) -> tuple[list[str], bool]:
    answer = c.get(f"/documents/{doc}/search", params={"q": q, "limit": limit})
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["count"] == len(body["items"])
    return [item["id"] for item in body["items"]], body["more"]


def _truth(texts: dict[str, str], q: str) -> list[str]:
    words = q.casefold().split()
    return [i for i, t in texts.items() if all(w in t.casefold() for w in words)]


def test_search_finds_every_word_in_any_case_in_document_order(document):
    c, _, _ = document
    doc = c.post("/documents", json={"name": "texts"}).json()["id"]
    rng = random.Random(3)
    texts = [rng.choice(TEXTS) + " " + rng.choice(TEXTS) for _ in range(300)]
    _import(c, doc, texts)
    by_id = {f"w{k}": t for k, t in enumerate(texts)}
    for q in (
        "revenue",
        "REVENUE quarterly",
        "école",
        "ÉCOLE paris",
        '"quoted"',
        "back\\slash",
        "x",
        "nothing",
    ):
        assert _search(c, doc, q) == (_truth(by_id, q), False), q
    first, more = _search(c, doc, "revenue", limit=5)
    assert first == _truth(by_id, "revenue")[:5] and more is True


def test_edits_show_in_search_at_once_and_only_text_matches(document):
    c, _, _ = document
    doc = c.post("/documents", json={"name": "texts"}).json()["id"]
    _import(c, doc, ["alpha", "beta"])
    assert _search(c, doc, "revenue") == ([], False)  # an id or a kind is not text
    c.patch(f"/documents/{doc}/items/w0", json={"data": {"text": "gamma"}})
    c.put(
        f"/documents/{doc}/items/new",
        json={"x0": 0, "y0": 0, "x1": 1, "y1": 1, "data": {"text": "Gamma ray"}},
    )
    assert _search(c, doc, "gamma") == (["w0", "new"], False)
    c.delete(f"/documents/{doc}/items/w0")
    assert _search(c, doc, "alpha") == ([], False) and _search(c, doc, "gamma") == (["new"], False)


@pytest.mark.parametrize("q", ["", "   ", " ".join(["w"] * 33)])
def test_a_query_without_words_or_with_too_many_is_a_422(document, q):
    c, doc, _ = document
    answer = c.get(f"/documents/{doc}/search", params={"q": q})
    assert answer.status_code == 422 and ("word" in answer.text or "at least 1" in answer.text)
