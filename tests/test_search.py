"""Search: a phrase found within one text item or across consecutive ones, folded as people
type it (case, accents, ligatures, ß, full-width forms, typographic quotes and dashes), in
document order, a page at a time, against brute force over the texts (hypothesis over random
texts, splits and words joined across items); the options; a hit's box a line; edits,
imports and deletes; the query's cap; a pool of its own that never holds up a viewport."""

import threading
import time
import unicodedata

import numpy as np
import orjson
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from service import NDJSON, client

import app.routers.search
import app.search
import app.text
from app.items import Item, batch_of
from app.registry import Registry
from app.search import Options, search
from app.snapfile import SnapshotFiles
from app.snapshots import build
from app.table import ItemTable

# Pieces of text with what folding must see through: ligatures, ß, accents, case, full width.
PIECES = [
    "ﬁnancial",
    "Straße",
    "éÉté",
    "Quarterly",
    "REVENUE",
    "these",
    "first",
    "Ｆｕｌｌ",
    "café",
    "x",
    "a b",
]


def _brute(texts: list[str | None], query: str, joins: list[str | None] | None = None) -> list[list[int]]:
    """The items of each hit, by the definition: the text items' texts, folded the obvious way
    (NFKC, casefold, accents dropped, typographic quotes and dashes made plain, one space
    between words), joined by one space in order, or by none after an item that joins the next
    ("hyphen": its trailing hyphen dropped); every occurrence of the folded query, left to
    right, not overlapping."""
    typed = {"’": "'", "‘": "'", "“": '"', "”": '"', "–": "-", "—": "-", "‐": "-"}

    def folded(text: str) -> str:
        text = unicodedata.normalize("NFKD", unicodedata.normalize("NFKC", text).casefold())
        text = "".join(typed.get(c, c) for c in text if not unicodedata.combining(c))
        return " ".join(text.split())

    owner, stream = [], ""
    for k, text in enumerate(texts):
        f = folded(text or "")
        join = joins[k] if joins else None
        if join == "hyphen" and f.endswith("-"):
            f = f[:-1]
        if f:
            stream += f + ("" if join else " ")
            owner += [k] * (len(f) + (0 if join else 1))
    needle = folded(query)
    hits, i = [], 0
    while needle and (i := stream.find(needle, i)) >= 0:
        hits.append(sorted(set(owner[i : i + len(needle)])))
        i += len(needle)
    return hits


def _snapshot(texts: list[str | None], joins: list[str | None] | None = None, boxes=None):
    """A snapshot of text items ``w0``, ``w1``... side by side on one line (or at ``boxes``),
    each joining the next as ``joins`` says."""
    data = [
        ({"text": t} | ({"join": joins[k]} if joins and joins[k] else {})) if t is not None else None
        for k, t in enumerate(texts)
    ]
    bodies = [
        orjson.dumps({"id": f"w{k}", "kind": "text", **({"data": d} if d is not None else {})})
        for k, d in enumerate(data)
    ]
    boxes = boxes or [[k, 0, k + 1, 1] for k in range(len(texts))]
    return build(ItemTable.of([f"w{k}" for k in range(len(texts))], np.array(boxes, float), bodies), 1, None)


def _all_hits(snap, query: str, limit: int = 3, options: Options | None = None) -> list[list[int]]:
    """Every hit, page after page."""
    hits, cursor, options = [], None, options or Options()
    while True:
        page = search(snap, query, limit, cursor, options)
        hits += [h.positions for h in page.hits]
        if not page.more:
            return hits
        cursor = page.cursor


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    words=st.lists(st.sampled_from(PIECES), min_size=1, max_size=30),
    splits=st.lists(st.booleans(), min_size=30, max_size=30),
    joins=st.lists(st.sampled_from([None, None, None, "word", "hyphen"]), min_size=34, max_size=34),
    blanks=st.lists(st.sampled_from([None, "", "  "]), max_size=4),
    start=st.integers(0, 29),
    length=st.integers(1, 4),
)
def test_phrases_across_items_are_found_as_brute_force_finds_them(
    words, splits, joins, blanks, start, length
):
    texts: list[str | None] = []
    for k, word in enumerate(words):  # words split into items at random: a line, or one item per word
        if not texts or splits[k] or texts[-1] is None:
            texts.append(word)
        else:
            texts[-1] += " " + word
    texts[1:1] = blanks  # items without text break nothing
    joins = joins[: len(texts)]
    texts = [t + "-" if t and j == "hyphen" else t for t, j in zip(texts, joins, strict=True)]
    query = " ".join(words[start % len(words) :][:length]).upper()
    snap = _snapshot(texts, joins)
    assert _all_hits(snap, query) == _brute(texts, query, joins), (texts, joins, query)
    page = search(snap, query, 1000)
    assert page.total == len(_brute(texts, query, joins)) and page.total_exact


def test_folding_sees_ligatures_eszett_accents_and_full_width():
    snap = _snapshot(["the ﬁnancial year", "Straße", "éÉté", "ＦＵＬＬ width", "Café"])
    for query, found in [("financial", [[0]]), ("strasse", [[1]]), ("éét", [[2]]), ("eet", [[2]]),
                         ("full", [[3]]), ("year strasse eete", [[0, 1, 2]]), ("cafe", [[4]])]:  # fmt: skip
        assert _all_hits(snap, query) == found, query


def test_the_options_match_case_accents_and_whole_words():
    snap = _snapshot(["Café", "cafe", "CAFÉ", "cafés", "the café"])
    assert _all_hits(snap, "café") == [[0], [1], [2], [3], [4]]
    assert _all_hits(snap, "café", options=Options(accents="match")) == [[0], [2], [3], [4]]
    assert _all_hits(snap, "Café", options=Options(case="match")) == [[0]]
    assert _all_hits(snap, "café", options=Options(case="match", accents="match")) == [[3], [4]]
    assert _all_hits(snap, "cafe", options=Options(whole="words")) == [[0], [1], [2], [4]]


def test_typed_quotes_apostrophes_and_dashes_find_the_typographic_ones_and_back():
    """People type ' and " and -; documents hold ’ ‘ “ ” – —. Either finds the other."""
    snap = _snapshot(["It doesn’t", "‘single’", "“double”", "pages 12–15", "a—dash", "it's", "a-b"])
    for query, found in [
        ("doesn't", [[0]]), ("doesn’t", [[0]]), ("'single'", [[1]]), ('"double"', [[2]]),
        ("12-15", [[3]]), ("a-dash", [[4]]), ("it’s", [[5]]), ("a–b", [[6]]),
    ]:  # fmt: skip
        assert _all_hits(snap, query) == found, query
    # a prime is an apostrophe to a keyboard; invisible marks are nothing
    assert _all_hits(_snapshot(["5′ tall", "hy\u00adphen"]), "5' tall hyphen") == [[0, 1]]


def test_matched_accents_keep_quotes_and_dashes_as_typed_matched_case_does_not():
    """``accents=match`` keeps what was typed: a straight apostrophe finds straight ones, a
    curly one curly ones, as é finds é and not e; ``case=match`` is about letters only."""
    snap = _snapshot(["doesn’t", "doesn't", "Doesn’t", "12–15", "12-15"])
    accents, case = Options(accents="match"), Options(case="match")
    assert _all_hits(snap, "doesn't", options=accents) == [[1]]
    assert _all_hits(snap, "doesn’t", options=accents) == [[0], [2]]
    assert _all_hits(snap, "12–15", options=accents) == [[3]]
    assert _all_hits(snap, "doesn't", options=case) == [[0], [1]]
    assert _all_hits(snap, "Doesn't", options=case) == [[2]]


def test_a_word_across_items_is_found_whole_hyphen_dropped_or_kept_as_the_join_says():
    texts = ["the", "encap-", "sulates", "from", "2008-", "02", "on", "Multi", "ply", "lines"]
    joins = [None, "hyphen", None, None, "word", None, None, "word", None, None]
    snap = _snapshot(texts, joins)
    for query, found in [
        ("encapsulates", [[1, 2]]), ("the encapsulates from", [[0, 1, 2, 3]]), ("2008-02", [[4, 5]]),
        ("Multiply lines", [[7, 8, 9]]), ("encap-sulates", []), ("encap sulates", []), ("200802", []),
        ("sulates", [[2]]),
    ]:  # fmt: skip
        assert _all_hits(snap, query) == found, query
    assert _all_hits(snap, "encap", options=Options(whole="words")) == []  # a piece is not a word
    assert _all_hits(snap, "Multiply", options=Options(case="match", whole="words")) == [[7, 8]]
    [hit] = search(snap, "capsul", 10).hits
    assert hit.text == "encapsulates"  # as a reader reads it
    assert _all_hits(_snapshot(["x-", "y"], ["bogus", None]), "x- y") == [[0, 1]]  # not a join: a space


def test_a_hit_has_one_box_a_line_it_covers():
    """A phrase that wraps is marked on each line: each line's box is the union of its items
    there, and ``box`` the union of all."""
    boxes = [[0, 0, 50, 10], [55, 0, 70, 10], [75, 1, 90, 10], [0, 14, 20, 24], [25, 14, 60, 24]]
    snap = _snapshot(["interfaces", "on", "en-", "top", "of"], [None, None, "hyphen", None, None], boxes)
    [hit] = search(snap, "interfaces on entop of", 10).hits
    assert hit.boxes == [(0.0, 0.0, 90.0, 10.0), (0.0, 14.0, 60.0, 24.0)]
    assert hit.box == (0.0, 0.0, 90.0, 24.0)
    [one] = search(snap, "on", 10).hits
    assert one.boxes == [one.box] == [(55.0, 0.0, 70.0, 10.0)]
    columns = [[0, 0, 10, 10], [100, 0, 110, 10], [50, 0, 60, 10]]  # the next item back to the left
    assert search(_snapshot(["a", "b", "c"], boxes=columns), "a b c", 1).hits[0].boxes == [
        (0.0, 0.0, 110.0, 10.0),
        (50.0, 0.0, 60.0, 10.0),
    ]


def _import(c, doc, texts: list[str]) -> None:
    lines = [
        orjson.dumps(
            {"id": f"w{k}", "x0": k, "y0": 0, "x1": k + 1, "y1": 1, "kind": "text", "data": {"text": t}}
        )
        for k, t in enumerate(texts)
    ]
    lines.append(orjson.dumps({"id": "revenue-id", "x0": 0, "y0": 0, "x1": 1, "y1": 1, "kind": "revenue"}))
    assert c.post(f"/documents/{doc}/items", content=b"\n".join(lines), headers=NDJSON).status_code == 200


def _hits(c, doc, q: str, **params) -> list[list[str]]:
    answer = c.get(f"/documents/{doc}/search", params={"q": q, **params})
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["count"] == len(body["hits"])
    assert {i["id"] for i in body["items"]} == {i for h in body["hits"] for i in h["ids"]}
    return [h["ids"] for h in body["hits"]]


def test_a_phrase_across_words_has_its_items_box_and_text_over_http(document):
    c, _, _ = document
    doc = c.post("/documents", json={"name": "line"}).json()["id"]
    _import(c, doc, ["Revenue", "grew:", "these", "first", "quarterly", "numbers"])
    body = c.get(f"/documents/{doc}/search", params={"q": "THESE first"}).json()
    assert body["hits"] == [
        {
            "ids": ["w2", "w3"],
            "box": [2.0, 0.0, 4.0, 1.0],
            "boxes": [[2.0, 0.0, 4.0, 1.0]],
            "text": "these first",
        }
    ]
    assert body["total"] == 1 and body["more"] is False and body["cursor"] is None
    assert _hits(c, doc, "revenue") == [["w0"]]  # an id or a kind is not text


def test_a_wrapped_phrase_has_a_box_for_each_line_over_http_and_joins_follow_edits(document):
    c, _, _ = document
    doc = c.post("/documents", json={"name": "wrapped"}).json()["id"]
    lines = [
        {"id": "a", "x0": 400, "y0": 100, "x1": 460, "y1": 112, "data": {"text": "interfaces"}},
        {"id": "b", "x0": 465, "y0": 100, "x1": 480, "y1": 112, "data": {"text": "on"}},
        {"id": "c", "x0": 72, "y0": 114, "x1": 90, "y1": 126, "data": {"text": "top"}},
        {"id": "d", "x0": 95, "y0": 114, "x1": 140, "y1": 126, "data": {"text": "encap-", "join": "hyphen"}},
        {"id": "e", "x0": 72, "y0": 128, "x1": 120, "y1": 140, "data": {"text": "sulates"}},
    ]
    body = b"\n".join(orjson.dumps(item) for item in lines)
    assert c.post(f"/documents/{doc}/items", content=body, headers=NDJSON).status_code == 200
    [hit] = c.get(f"/documents/{doc}/search", params={"q": "interfaces on top"}).json()["hits"]
    assert hit["boxes"] == [[400.0, 100.0, 480.0, 112.0], [72.0, 114.0, 90.0, 126.0]]
    assert hit["box"] == [72.0, 100.0, 480.0, 126.0] and hit["text"] == "interfaces on top"
    assert _hits(c, doc, "encapsulates") == [["d", "e"]]
    c.patch(f"/documents/{doc}/items/d", json={"data": {"text": "encap-"}})  # no join: a space again
    assert _hits(c, doc, "encapsulates") == [] and _hits(c, doc, "encap- sulates") == [["d", "e"]]
    c.patch(f"/documents/{doc}/items/b", json={"data": {"text": "on", "join": "word"}})
    assert _hits(c, doc, "ontop") == [["b", "c"]]  # an edit's join counts, where it stands


def test_hits_page_through_with_a_cursor_of_their_version(document):
    c, _, _ = document
    doc = c.post("/documents", json={"name": "many"}).json()["id"]
    _import(c, doc, ["alpha beta"] * 7)
    first = c.get(f"/documents/{doc}/search", params={"q": "beta alpha", "limit": 4}).json()
    pairs = [[f"w{k}", f"w{k + 1}"] for k in range(6)]  # each item's "beta" and the next one's "alpha"
    assert [h["ids"] for h in first["hits"]] == pairs[:4] and first["total"] == 6 and first["more"]
    rest = c.get(
        f"/documents/{doc}/search", params={"q": "beta alpha", "limit": 4, "cursor": first["cursor"]}
    )
    assert [h["ids"] for h in rest.json()["hits"]] == pairs[4:] and rest.json()["more"] is False
    assert rest.json()["total"] == 6  # counted by the first page, carried by its cursor
    c.put(f"/documents/{doc}/items/w9", json={"x0": 0, "y0": 0, "x1": 1, "y1": 1})
    stale = c.get(f"/documents/{doc}/search", params={"q": "beta", "cursor": first["cursor"]})
    assert stale.status_code == 409 and "search again" in stale.json()["detail"]
    bad = c.get(f"/documents/{doc}/search", params={"q": "beta", "cursor": "1.2"})
    assert bad.status_code == 422 and "cursor" in bad.json()["detail"]


def test_edits_imports_and_deletes_keep_document_order(document):
    c, _, _ = document
    doc = c.post("/documents", json={"name": "order"}).json()["id"]
    _import(c, doc, ["alpha one", "beta", "alpha two", "gamma"])
    c.patch(f"/documents/{doc}/items/w1", json={"data": {"text": "alpha edited"}})
    assert _hits(c, doc, "alpha", limit=1) == [["w0"]]
    assert _hits(c, doc, "alpha") == [["w0"], ["w1"], ["w2"]]  # the edited item where it stands
    assert _hits(c, doc, "edited alpha two") == [["w1", "w2"]]  # a phrase across an edited item
    c.put(f"/documents/{doc}/items/new", json={"x0": 0, "y0": 0, "x1": 1, "y1": 1, "data": {"text": "Alpha"}})
    c.delete(f"/documents/{doc}/items/w0")
    assert _hits(c, doc, "alpha") == [["w1"], ["w2"], ["new"]]
    assert _hits(c, doc, "one") == []
    extra = orjson.dumps({"id": "late", "x0": 5, "y0": 0, "x1": 6, "y1": 1, "data": {"text": "alpha late"}})
    assert c.post(f"/documents/{doc}/items", content=extra, headers=NDJSON).status_code == 200  # an import
    assert _hits(c, doc, "alpha") == [["w1"], ["w2"], ["new"], ["late"]]


@pytest.mark.parametrize(
    ("q", "said"), [("", "at least 1"), ("   ", "give some text"), ("x" * 1001, "at most 1000")]
)
def test_an_empty_or_overlong_query_is_a_422(document, q, said):
    c, doc, _ = document
    answer = c.get(f"/documents/{doc}/search", params={"q": q})
    assert answer.status_code == 422 and said in answer.text


def test_a_long_query_costs_one_pass_not_one_per_word(monkeypatch):
    """An attack pass found that one 200-character query of 32 non-ASCII words cost ~10 s on the
    1M demo (up to 4 needles a word, each a full pass): 40 at once starved every request."""
    passes = []
    real = app.text.TextIndex.find

    def counted(self, needle, start=0):
        passes.append(needle)
        return real(self, needle, start)

    monkeypatch.setattr(app.text.TextIndex, "find", counted)
    snap = _snapshot(["été " * 50] * 100)
    search(snap, " ".join(["Ééé"] * 32), 20)
    assert len(passes) == 1  # the page's, which goes on to count: whatever the words


def test_stuck_searches_hold_up_no_other_request_and_past_the_queue_are_a_503(data_dir, monkeypatch):
    """More stuck searches than the shared thread pool has threads (40): viewports, item reads
    and /health answer all the same, for searches run in a pool of their own."""
    monkeypatch.setenv("VANTAGE_SEARCH_THREADS", "1")
    monkeypatch.setenv("VANTAGE_SEARCH_QUEUE", "44")
    released, started = threading.Event(), threading.Semaphore(0)
    real = app.search.search

    def stuck(*args, **kwargs):
        started.release()
        released.wait(60)
        return real(*args, **kwargs)

    monkeypatch.setattr(app.routers.search, "search", stuck)
    with client() as c:
        doc = c.post("/documents", json={"name": "d"}).json()["id"]
        _import(c, doc, ["alpha"])
        search = lambda: c.get(f"/documents/{doc}/search", params={"q": "alpha"})
        waiting = [threading.Thread(target=search) for _ in range(45)]  # 1 runs, 44 wait
        for thread in waiting:
            thread.start()
        assert started.acquire(timeout=30)  # one is stuck in the pool
        time.sleep(0.5)  # the others have queued
        busy = search()
        assert busy.status_code == 503 and busy.headers["retry-after"] == "1", busy.text
        assert "VANTAGE_SEARCH_THREADS" in busy.text
        others = {}

        def ask() -> None:
            others["viewport"] = c.get(
                f"/documents/{doc}/viewport", params={"x0": 0, "y0": 0, "x1": 5, "y1": 5}
            )
            others["item"] = c.get(f"/documents/{doc}/items/w0")
            others["health"] = c.get("/health")

        asking = threading.Thread(target=ask)
        asking.start()
        asking.join(20)  # held up, it would wait for the searches: 60 s
        released.set()
        assert {k: r.status_code for k, r in others.items()} == {"viewport": 200, "item": 200, "health": 200}
        for thread in waiting:
            thread.join(60)


def test_either_store_searches_alike_in_this_process_and_another(open_store, tmp_path):
    """The text index is built from whichever store holds the document, and another process
    (a worker, a replica) that catches up with the edits finds the same hits."""
    texts = ["these", "first", "words", "these first", "again"]
    items = [Item(f"w{k}", k, 0, k + 1, 1, "text", data={"text": t}) for k, t in enumerate(texts)]
    here = Registry(open_store(), SnapshotFiles(tmp_path / "here"), budget=1 << 30)
    doc = here.create("d")
    doc.import_items([batch_of(items, 4096)])
    doc.patch("w2", {"data": {"text": "these"}}, 4096)
    doc.delete("w4")
    want = _brute(["these", "first", "these", "these first"], "these first")  # as edited
    assert want == [[0, 1], [3]]
    assert [h.positions for h in search(doc.snapshot, "these first", 10).hits] == want
    there = Registry(open_store(), SnapshotFiles(tmp_path / "there"), budget=1 << 30)[doc.id]
    assert [h.positions for h in search(there.snapshot, "these first", 10).hits] == want
    assert [h.positions for h in search(there.snapshot, "again", 10).hits] == []


def test_an_edited_item_is_found_where_it_stood_and_a_new_one_after_the_others(data_dir):
    """Items imported in an order unlike their tree's (right to left), served from the mapped
    file after a restart: an edit keeps its item's place in document order."""
    lines = [
        orjson.dumps(
            {
                "id": f"w{k}",
                "x0": 900 - 90 * k,
                "y0": 0,
                "x1": 950 - 90 * k,
                "y1": 9,
                "data": {"text": "word"},
            }
        )
        for k in range(10)
    ]
    with client() as c:
        doc = c.post("/documents", json={"name": "order"}).json()["id"]
        assert c.post(f"/documents/{doc}/items", content=b"\n".join(lines), headers=NDJSON).status_code == 200
    with client() as c:
        assert (
            c.patch(f"/documents/{doc}/items/w0", json={"data": {"text": "word edited"}}).status_code == 200
        )
        assert _hits(c, doc, "word", limit=3) == [["w0"], ["w1"], ["w2"]]
        c.put(
            f"/documents/{doc}/items/new", json={"x0": 0, "y0": 0, "x1": 1, "y1": 1, "data": {"text": "word"}}
        )
        assert c.patch(f"/documents/{doc}/items/w9", json={"x0": 2000, "x1": 2001}).status_code == 200
        assert _hits(c, doc, "word", limit=20)[-3:] == [["w8"], ["w9"], ["new"]]


def test_an_item_edited_then_deleted_is_no_longer_found(data_dir):
    with client() as c:
        doc = c.post("/documents", json={"name": "gone"}).json()["id"]
        _import(c, doc, ["alpha", "beta", "alpha again"])
        assert (
            c.patch(f"/documents/{doc}/items/w1", json={"data": {"text": "alpha edited"}}).status_code == 200
        )
        assert _hits(c, doc, "alpha") == [["w0"], ["w1"], ["w2"]]
        assert c.delete(f"/documents/{doc}/items/w1").status_code == 200
        assert _hits(c, doc, "alpha") == [["w0"], ["w2"]]
        assert _hits(c, doc, "edited") == []


def test_a_first_page_counts_hits_up_to_the_cap_and_no_further(monkeypatch):
    """The count goes on past the page only up to the cap: a word on every line of a large
    document costs the cap's steps, not one per hit."""
    monkeypatch.setattr(app.search, "TOTAL_CAP", 5)
    pulled = []
    real = app.text.TextIndex.find

    def counted(self, needle, start=0):
        for hit in real(self, needle, start):
            pulled.append(hit)
            yield hit

    monkeypatch.setattr(app.text.TextIndex, "find", counted)
    search(_snapshot(["alpha"] * 50), "alpha", 2)
    assert len(pulled) == 6  # the cap and one more, to know it is passed


def test_total_is_exact_up_to_the_cap_and_says_at_least_past_it(monkeypatch):
    monkeypatch.setattr(app.search, "TOTAL_CAP", 5)
    at_cap, past = search(_snapshot(["alpha"] * 5), "alpha", 2), search(_snapshot(["alpha"] * 8), "alpha", 2)
    assert (at_cap.total, at_cap.total_exact) == (5, True)
    assert (past.total, past.total_exact) == (5, False)
    rest = search(_snapshot(["alpha"] * 8), "alpha", 2, past.cursor)
    assert (rest.total, rest.total_exact) == (5, False)  # the first page's count, carried on


def test_whole_words_see_a_letter_beyond_ascii_on_either_side():
    snap = _snapshot(["дом", "ом", "до", "x ом, дома"])
    assert _all_hits(snap, "ом", options=Options(whole="words")) == [[1], [3]]
    assert _all_hits(snap, "до", options=Options(whole="words")) == [[2]]
    assert _all_hits(snap, "ом") == [[0], [1], [3], [3]]


def test_matched_accents_still_fold_full_width_forms_and_decomposed_accents():
    """NFKC makes full-width letters plain and composes decomposed accents, so `accents=match`
    compares the letters people see, however they were encoded."""
    snap = _snapshot(["Ｆｕｌｌ", "cafe\u0301", "café"])
    matched = Options(accents="match")
    assert _all_hits(snap, "full", options=matched) == [[0]]
    assert _all_hits(snap, "café", options=matched) == [[1], [2]]
    assert _all_hits(snap, "cafe\u0301", options=matched) == [[1], [2]]
    assert _all_hits(snap, "cafe", options=matched) == []


def test_a_phrase_is_found_across_the_scans_blocks(monkeypatch):
    """Blocks of 7 bytes: every phrase crosses a block's end somewhere, and each is found once."""
    monkeypatch.setattr(app.text, "FIND_BLOCK", 7)
    texts = ["these", "first", "quarterly", "numbers", "these first", "again", "these", "first"]
    snap = _snapshot(texts)
    for query in ["these first", "first quarterly numbers", "numbers these", "again these first", "e"]:
        assert _all_hits(snap, query) == _brute(texts, query), query


def test_a_query_folding_past_its_limit_is_a_422_that_says_so(document):
    """The limit is on the query as folded, in UTF-8: 513 Cyrillic letters (1,026 bytes) or
    342 `ﬃ` ligatures (`ffi` each) pass the 1,000 characters a query may have, not the
    1,024 bytes it may fold to."""
    c, doc, _ = document
    assert c.get(f"/documents/{doc}/search", params={"q": "я" * 512}).status_code == 200
    for q in ["я" * 513, "ﬃ" * 342]:
        answer = c.get(f"/documents/{doc}/search", params={"q": q})
        assert answer.status_code == 422, answer.text
        assert "q: 1026 bytes once folded; a query holds at most 1024" in answer.json()["detail"]
