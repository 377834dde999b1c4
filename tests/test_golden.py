"""Golden answers: a few fixed requests against a small seeded document, their bodies kept in
``tests/golden/`` and checked byte for byte (tippecanoe keeps its test output so): a zoomed-in
viewport, a diff of a pan and one of a zoom out, a zoomed-out viewport (aggregates and their
masks) and the same with ``tiles=true``, the tile it names, and a page of search hits.

An answer that changes, in a number's digits, a key's order or an entry's place, fails here
with the file, the first differing byte and the first differing JSON path. When the change is
meant, write the files again and read their diff before committing it:

    VANTAGE_GOLDEN=update .venv/bin/python -m pytest -q -n 0 tests/test_golden.py
    git diff --stat tests/golden/

The document is made in the test (two pages of ``scenes.long_document``, words with text), so
every answer is the same on every run: its version is 1, and its id (random) is in no answer.
A tile's layers are deflated by the zlib Python links: another zlib build (zlib-ng) may
deflate the same bits to other bytes, and the tile's file must be written again there.
"""

import os
from pathlib import Path

import orjson
import pytest
from service import NDJSON, client

from app.config import get_settings
from spatial import scenes

GOLDEN = Path(__file__).parent / "golden"
UPDATE = os.environ.get("VANTAGE_GOLDEN", "")
if UPDATE not in ("", "update"):
    raise ValueError(
        f"VANTAGE_GOLDEN={UPDATE!r}: set it to 'update' to write tests/golden/ again, or unset it"
    )

#: the words' text, in reading order: "revenue by" runs across two items 88 times
WORDS = ["Quarterly", "revenue", "by", "Region", "café", "totals", "the", "growth", "of", "net", "income"]

ZOOMED_OUT = {"x0": -200.0, "y0": -100.0, "x1": 800.0, "y1": 1200.0, "scale": 0.15, "min_px": 1}

#: golden file name: (route under /documents/{doc}, query parameters)
REQUESTS: dict[str, tuple[str, dict]] = {
    "viewport-zoomed-in": ("/viewport", {"x0": 60.0, "y0": 60.0, "x1": 260.0, "y1": 140.0, "scale": 2}),
    "diff-pan": ("/diff", {"from": "60,60,260,140", "to": "100,100,300,180", "scale": 2}),
    "diff-zoom-out": (
        "/diff",
        {"from": "60,60,260,140", "to": "-200,-100,800,1200", "from_scale": 2, "scale": 0.15, "min_px": 1},
    ),
    "viewport-zoomed-out": ("/viewport", ZOOMED_OUT),
    "viewport-zoomed-out-tiled": ("/viewport", {**ZOOMED_OUT, "tiles": "true"}),
    "tile-6-11-0-0": ("/tiles/6/11/0/0", {"version": 1}),  # viewport-zoomed-out-tiled names it
    "search-revenue-by": ("/search", {"q": "revenue by", "limit": 3}),
}


def _lines() -> bytes:
    """Two pages of words, images and frames as NDJSON; each word's text from WORDS in turn."""
    boxes, kinds = scenes.long_document(pages=2, seed=1)
    lines = []
    for i, ((x0, y0, x1, y1), kind) in enumerate(zip(boxes.tolist(), kinds.tolist(), strict=True)):
        item = {"id": f"i{i}", "x0": x0, "y0": y0, "x1": x1, "y1": y1, "kind": scenes.KINDS[kind], "z": i % 7}
        if kind == scenes.TEXT:
            item["data"] = {"text": WORDS[i % len(WORDS)]}
        lines.append(orjson.dumps(item) + b"\n")
    return b"".join(lines)


@pytest.fixture(scope="module")
def golden_document(tmp_path_factory):
    """A client and the document (its id): made with the default settings, whatever
    ``VANTAGE_*`` the environment holds, since a setting (the entry budget) changes answers."""
    with pytest.MonkeyPatch.context() as env:
        for name in [n for n in os.environ if n.startswith("VANTAGE_")]:
            env.delenv(name)
        env.setenv("VANTAGE_DATA_DIR", str(tmp_path_factory.mktemp("golden-data")))
        get_settings.cache_clear()
        with client() as c:
            doc = c.post("/documents", json={"name": "golden"}).json()["id"]
            imported = c.post(f"/documents/{doc}/items", content=_lines(), headers=NDJSON)
            assert imported.json() == {"imported": 975, "version": 1}, imported.text
            yield c, doc
        get_settings.cache_clear()


@pytest.mark.parametrize("name", list(REQUESTS))
def test_an_answer_is_its_golden_file_byte_for_byte(golden_document, name):
    c, doc = golden_document
    route, params = REQUESTS[name]
    first, again = (c.get(f"/documents/{doc}{route}", params=params) for _ in range(2))
    assert first.status_code == 200, first.text
    assert first.headers["content-type"] == "application/json"
    assert doc.encode() not in first.content, "the answer holds the document's id, which is random"
    # the second is often answered from a cache (zoomed-out answers, tiles): the same bytes
    assert again.content == first.content, _difference("the first answer", first.content, again.content)
    path = GOLDEN / f"{name}.json"
    if UPDATE:
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(first.content)
    if not path.exists():
        pytest.fail(f"{path} is missing: write it with VANTAGE_GOLDEN=update (tests/test_golden.py)")
    kept = path.read_bytes()
    if first.content != kept:
        pytest.fail(
            f"GET /documents/{{doc}}{route} {params} no longer answers {path}: "
            f"{_difference(path.name, kept, first.content)}\n"
            "If the change is meant: VANTAGE_GOLDEN=update .venv/bin/python -m pytest -n 0 "
            "tests/test_golden.py, then read git diff tests/golden/",
            pytrace=False,
        )


def test_the_tiled_answer_names_the_golden_tile(golden_document):
    """The tile kept is one the zoomed-out tiled answer sends a client to fetch."""
    c, doc = golden_document
    route, params = REQUESTS["viewport-zoomed-out-tiled"]
    answer = c.get(f"/documents/{doc}{route}", params=params).json()
    band, z, tx, ty = map(int, REQUESTS["tile-6-11-0-0"][0].split("/")[2:])
    tx0, ty0, tx1, ty1 = answer["tiles"]["range"]
    assert (answer["version"], answer["tiles"]["band"], answer["tiles"]["z"]) == (1, band, z)
    assert tx0 <= tx <= tx1 and ty0 <= ty <= ty1


def test_a_difference_is_named_by_its_byte_and_its_json_path():
    kept = b'{"items":[{"id":"i1","x0":1.5},{"id":"i2"}]}'
    assert _difference("f.json", kept, kept.replace(b"1.5", b"1.25")) == (
        'first difference at byte 28: f.json has \'1","x0":1.5},{"id":"i2"}]}\', '
        'the answer \'1","x0":1.25},{"id":"i2"}]}\'; '
        "at $.items[0].x0: 1.5 in f.json, 1.25 in the answer"
    )
    assert "at $.items: 2 entries in f.json, 1 in the answer" in _difference(
        "f.json", kept, b'{"items":[{"id":"i1","x0":1.5}]}'
    )
    assert "the same JSON in another order or spelling" in _difference(
        "f.json", kept, b'{"items": [{"x0":1.5,"id":"i1"},{"id":"i2"}]}'
    )
    assert "f.json is not JSON" in _difference("f.json", b"{", kept)


def _difference(name: str, kept: bytes, got: bytes) -> str:
    """Where ``got`` first differs from ``kept`` (named ``name``): the byte, and the JSON path."""
    at = next(
        (i for i, (a, b) in enumerate(zip(kept, got, strict=False)) if a != b), min(len(kept), len(got))
    )
    around = slice(max(0, at - 10), at + 20)
    text = (
        f"first difference at byte {at}: {name} has {kept[around].decode(errors='replace')!r}, "
        f"the answer {got[around].decode(errors='replace')!r}"
    )
    try:
        kept_json = orjson.loads(kept)
    except orjson.JSONDecodeError as error:
        return f"{text}; {name} is not JSON ({error})"
    where = _json_difference(kept_json, orjson.loads(got), "$", name)
    return f"{text}; {where or 'the same JSON in another order or spelling (keys, numbers, spaces)'}"


def _json_difference(kept, got, path: str, name: str) -> str | None:
    """The first place ``got`` differs from ``kept``, as a JSON path and the two values."""
    if type(kept) is not type(got):
        return f"at {path}: {_short(kept)} in {name}, {_short(got)} in the answer"
    if isinstance(kept, dict):
        for key in [*kept, *(k for k in got if k not in kept)]:
            if key not in kept or key not in got:
                side = name if key in kept else "the answer"
                return f"at {path}: only {side} has the key {key!r}"
            found = _json_difference(kept[key], got[key], f"{path}.{key}", name)
            if found:
                return found
        return None
    if isinstance(kept, list):
        for i, (a, b) in enumerate(zip(kept, got, strict=False)):
            found = _json_difference(a, b, f"{path}[{i}]", name)
            if found:
                return found
        if len(kept) != len(got):
            return f"at {path}: {len(kept)} entries in {name}, {len(got)} in the answer"
        return None
    return None if kept == got else f"at {path}: {_short(kept)} in {name}, {_short(got)} in the answer"


def _short(value) -> str:
    """``value``'s repr, cut to 60 characters (a mask's bits run to thousands)."""
    text = repr(value)
    return text if len(text) <= 60 else f"{text[:57]}..."
