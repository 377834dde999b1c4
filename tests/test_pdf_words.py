"""A PDF's words read as a reader reads them: PDFs written here (tests/pdfs.py) with each kind of
break a line end makes (between lowercase letters, a compound, a number range, a soft hyphen,
U+2010, U+FFFE) and each way a layout splits a word (kerning, a change of font, letters spaced
out or placed one by one), each found as expected and drawn where the PDF draws it; then real
manuals of several producers, searched against pdftotext's text as the oracle."""

import shutil
from pathlib import Path

import orjson
import pytest
from pdfs import document, line, page, width

from app.importers import Source, batches, detect
from app.search import search
from benchmarks.pdf_words import CORPUS, LIBREOFFICE, measure, snapshot


def _spaced(x: float, y: float, words: list[str], letters: int, words_apart: int, font: str = "F4") -> str:
    """Text whose letters a ``TJ`` puts ``letters`` thousandths of an em apart, and its words
    ``words_apart``: a code listing's columns."""
    parts = []
    for i, word in enumerate(words):
        parts += [f"({ch}) -{letters}" for ch in word]
        parts[-1] = parts[-1].rsplit(" ", 1)[0] + (f" -{words_apart}" if i < len(words) - 1 else "")
    return f"BT /{font} 12 Tf {x} {y} Td [{' '.join(parts)}] TJ ET"


BREAKS = page(  # a line 14 pt below the one before
    line(72, 700, "The context struct encap-"),  # lowercase and lowercase: PDFium marks it U+FFFE
    line(72, 686, "sulates all information; an object-"),
    line(72, 672, "oriented design beside object-oriented code"),  # the page spells it with its hyphen
    line(72, 658, "from 2008-"),  # digits: the hyphen is the number's
    line(72, 644, "02 on pages 12-"),
    line(72, 630, "15 of the X-"),  # a capital: kept
    line(72, 616, "Window system, a hy-", "F5"),  # U+2010
    "BT /F1 12 Tf 72 602 Td (phen and a mark) Tj /F7 12 Tf (-) Tj ET",  # U+FFFE
    "BT /F1 12 Tf 72 588 Td (ers with ISBN 978) Tj /F6 12 Tf (-) Tj ET",  # a soft hyphen
    "BT /F1 12 Tf 72 574 Td (3 and soft hy) Tj /F6 12 Tf (-) Tj /F1 12 Tf (phens mid-line.) Tj ET",
    line(72, 560, "an identifier ChangeStarting-"),  # broken before a capital, within its humps
    line(72, 546, "Value, and MulByS-"),  # or after one (as LibreOffice's hyphenation breaks them)
    line(72, 532, "tartingValue too"),
)
SPLITS = page(
    "BT /F8 12 Tf 72 700 Td [(CrcW) -344 (ordByW) -344 (ordBlocks) ( runs)] TJ ET",  # kerned: gaps PDFium sees
    "BT /F8 12 Tf 72 680 Td [(NetW) -344] TJ /F2 12 Tf (ork) Tj /F1 12 Tf ( links) Tj ET",  # a font change
    _spaced(72, 660, ["InitWordTables", "void"], 130, 650),  # a listing's letters, PDFium spaces out
    _spaced(72, 640, ["sizeof", "buffer"], 130, 650),
    " ".join(
        f"BT /F1 12 Tf {72 + width('placed'[:i]):.2f} 620 Td ({ch}) Tj ET" for i, ch in enumerate("placed")
    )
    + " BT /F1 12 Tf 120 620 Td (letters) Tj ET",  # letters placed one by one
    # a bullet, prose, a code word in a smaller font, on one line
    "BT /F1 9 Tf 72 560 Td (o) Tj /F1 12 Tf 12 0 Td (Call) Tj /F4 9 Tf ( strlen) Tj /F1 12 Tf ( to count) Tj ET",
    # names a word space apart, set smaller than the line's first word (a definition's, as texinfo sets them)
    "BT /F1 14 Tf 72 600 Td [(Key) -400] TJ /F1 10 Tf [(d) -280 (p) -280 (q) -280 (a) -280 (b) -280 (c)"
    " -900 (names)] TJ ET",
)


@pytest.fixture(scope="module")
def pdf(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("pdf") / "breaks.pdf"
    path.write_bytes(document([BREAKS, SPLITS]))
    return path


@pytest.fixture(scope="module")
def items(pdf) -> dict[str, dict]:
    """The text items the importer makes of ``pdf``, by id, in order."""
    out = {}
    for batch in batches(Source.of(pdf), detect(pdf), 1 << 16, 4096):
        for body in batch.bodies:
            item = orjson.loads(body)
            if item["kind"] == "text":
                out[item["id"]] = item
    return out


@pytest.fixture(scope="module")
def snap(pdf):
    return snapshot(pdf)


def _word(items: dict[str, dict], text: str) -> dict:
    [item] = [i for i in items.values() if i["data"]["text"] == text]
    return item


def test_a_word_broken_at_a_line_end_is_one_word_whose_pieces_stay_on_their_lines(items, snap):
    head, tail = _word(items, "encap-"), _word(items, "sulates")
    assert head["data"] == {"text": "encap-", "join": "hyphen"}  # drawn as the PDF draws it
    # each on its own line (line-high boxes may touch, where the lines are set close)
    assert (head["y0"] + head["y1"]) / 2 < tail["y0"] and tail["x0"] < head["x0"]
    assert head["y1"] - head["y0"] < 18 and tail["y1"] - tail["y0"] < 18  # a line tall, not two
    [hit] = search(snap, "encapsulates", 10).hits
    assert [snap.item_id(p) for p in hit.positions] == [head["id"], tail["id"]]
    assert hit.text == "encapsulates"
    assert hit.boxes == [
        tuple(head[k] for k in ("x0", "y0", "x1", "y1")),
        tuple(tail[k] for k in ("x0", "y0", "x1", "y1")),
    ]


@pytest.mark.parametrize(
    ("query", "hits"),
    [
        ("encapsulates", 1),  # lowercase and lowercase: the hyphen only breaks the word
        ("object-oriented", 2),  # broken at a line end and spelt with its hyphen on the page
        ("objectoriented", 0),
        ("2008-02", 1),  # a date: its hyphen stays
        ("200802", 0),
        ("12-15", 1),  # a number range
        ("X-Window", 1),  # a capital after the hyphen
        ("hyphen and", 1),  # U+2010 at the line end, between lowercase letters
        ("markers", 1),  # U+FFFE, a hyphen's glyph mapped to it
        ("9783", 1),  # a soft hyphen: only ever a break
        ("soft hyphens mid-line", 1),  # a soft hyphen within a line is nothing
        ("ChangeStartingValue", 1),  # an identifier's humps, broken at a line end
        ("MulByStartingValue", 1),
        ("ChangeStarting-Value", 0),
    ],
)
def test_each_kind_of_line_end_hyphen_reads_as_a_reader_reads_it(snap, query, hits):
    assert search(snap, query, 10).total == hits, query


def test_no_item_holds_a_soft_hyphen_or_a_missing_glyph(items):
    texts = [i["data"]["text"] for i in items.values()]
    assert not [t for t in texts if "\u00ad" in t or "\ufffe" in t or not t.isprintable()]
    assert {"mark-", "978-", "hy\u2010"} <= set(texts)  # the hyphens drawn: U+FFFE and U+00AD as "-"
    joins = {i["data"]["text"]: i["data"].get("join") for i in items.values()}
    assert [joins[w] for w in ("2008-", "12-", "X-", "hy\u2010", "mark-", "978-")] == [
        "word", "word", "word", "hyphen", "hyphen", "hyphen",
    ]  # fmt: skip


@pytest.mark.parametrize(
    "word", ["CrcWordByWordBlocks", "NetWork", "InitWordTables", "void", "sizeof", "buffer", "placed"]
)
def test_pieces_of_a_word_the_layout_split_are_one_word(items, snap, word):
    assert search(snap, word, 10).total == 1, word
    assert _word(items, word)  # one item: drawn as one word


def test_the_words_of_a_line_are_as_tall_as_one_another_whatever_their_fonts(items):
    """Each as tall as its font's line, not its glyphs' ink ("Call" beside "to"), then as the
    words side by side (a code word and a bullet in smaller fonts): a page drawing text by its
    height draws the whole line as text or the whole line as bars."""
    line = [_word(items, w) for w in ("o", "Call", "strlen", "to", "count")]
    assert len({(w["y0"], w["y1"]) for w in line}) == 1, [(w["data"]["text"], w["y0"], w["y1"]) for w in line]
    baseline = 792 + 24 + (792 - 560)  # on the second page, below the first and the gap
    assert baseline - 12.5 < line[0]["y0"] < baseline - 10  # 12 pt type's ascent, not 9 pt's


def test_lone_letters_a_word_space_apart_stay_words(items, snap):
    assert search(snap, "Key d p q a b c names", 10).total == 1 and search(snap, "dpq", 10).total == 0


# -- real manuals ------------------------------------------------------------------------------

# pdftotext runs a subscript into its base (x_{n_k}: "xnk"), which the PDF draws apart
FORMULAS = {"crc-doc.1.0.pdf": {"xnk", "xnw"}}


@pytest.mark.parametrize(
    ("package", "path"),
    [
        pytest.param(package, path, marks=pytest.mark.slow(seconds=20) if "valgrind" in path else ())
        for package, path in [*CORPUS[:4], ("", str(LIBREOFFICE))]
    ],
    ids=lambda value: Path(value).name if "/" in value else None,
)
def test_real_manuals_find_words_as_pdftotext_finds_them(package, path):
    """Debian's manuals, by TeX (texinfo; a code listing's spaced-out letters), PassiveTeX and
    DocBook through Apache FOP, and a LibreOffice document hyphenated as Writer hyphenates: for a seeded sample of pdftotext's words, Vantage's hits equal
    pdftotext's count for 97% or more (pdftotext leaves a listing's letters spaced out, which
    Vantage reads whole: counted with them); a word Vantage never finds is one it reads with the
    hyphen the page spells it with (pdftotext drops every line-end hyphen); every apostrophe
    typed straight finds its curly form."""
    if shutil.which("pdftotext") is None:
        pytest.skip("pdftotext is missing: apt-get install poppler-utils (.ci/setup-env installs it)")
    if not Path(path).exists():
        pytest.skip(f"{path} is missing: apt-get install {package} (.ci/setup-env installs it)")
    figures = measure(Path(path))
    assert figures.same_spaced >= 0.97 * len(figures.counts), figures.counts
    unfound = set(figures.never) - FORMULAS.get(figures.name, set())
    snap = snapshot(Path(path)) if unfound else None
    for word in unfound:  # found with the hyphen the page spells it with: chacha-poly1305
        hyphenated = (word[:i] + "-" + word[i:] for i in range(1, len(word)))
        assert any(search(snap, w, 1).total for w in hyphenated), f"{word!r} never found"
    assert figures.found == len(figures.apostrophes), figures.apostrophes
