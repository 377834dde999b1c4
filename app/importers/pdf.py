"""PDF pages as canvas items, read with pypdfium2 (PDFium): each page's frame (kind "page"),
its words (kind "text", the word in ``data``), images (kind "image") and drawings (kind
"drawing": paths and shadings that paint something). Pages are stacked top to bottom with a
gap, or laid out in ``columns`` side by side (left to right, then down), in points; PDF's y,
which grows upward from the page's bottom, is flipped so it grows downward like the canvas's,
and a page's /Rotate is applied as a viewer shows it.

Words are read as a reader reads them. PDFium's characters are split at whitespace (PDFium
puts a space or a line break where the layout has a gap); a word's box is the union of its
characters' boxes, as tall as its font's line (descent to ascent, not the glyphs' ink), then
as its line, the words side by side (a code word, a bullet, a sign set large): the words of a
line are as tall as one another. Then:

- Pieces of one word that the layout split, which PDFium took for words (kerning, a change of
  font mid-word, letters placed one by one or spaced out), are one item. On a line, a space
  PDFium made up (the PDF holds no space there) joins the pieces beside it where their gap is
  under KERN em, or, on a line of letter-spaced text, as narrow as its letters' gaps (see
  ``_letter_gap``).
- A word broken at a line end stays two items, each on its own line and drawn as the PDF
  draws it, hyphen included (PDFium's U+FFFE mark of a line-end hyphen, and a soft hyphen,
  are stored as ``-``); the first piece's ``data.join`` says the next goes on with the same
  word (see :mod:`app.text`): "hyphen" where the hyphen only breaks the word, "word" where it
  belongs to it. The page decides where it spells the word elsewhere (``object-oriented``;
  ``MulByPowD``); else a soft hyphen only breaks (where PDFium left it: its mark hides which
  hyphen it was), and so does a hyphen after a lowercase letter and before one (as PDF.js
  reads it) or before an identifier's capitals (``Fc-``/``ConfigLoadAndParse``), or within
  an identifier's humps beside a capital, as LibreOffice hyphenates them
  (``ChangeStarting-``/``Value``, ``ChangeS-``/``tartingValue``); one beside a digit or
  another capital belongs (``2008-``/``02``, ``X-``/``Window``).
- A soft hyphen within a line is dropped: it shows only where a line breaks.
"""

from __future__ import annotations

import ctypes
import itertools
import multiprocessing
import re
from bisect import bisect_right
from collections.abc import Callable, Iterable, Iterator
from functools import partial
from pathlib import Path

from ..items import Batch, Item, batch_of
from .base import ImportFailed, Matrix, Source, apply, bounds, compose, processes

__all__ = ["NAME", "SUFFIXES", "detect", "read"]

NAME = "PDF"
SUFFIXES = (".pdf",)
GAP = 24.0  # points between pages
MAX_WORD = 900  # characters of a word kept in its data (a PDF may hold a "word" of megabytes)
KERN = 0.1  # em: a made-up space over a narrower gap is no space (Xpdf's word spacing, too)
LETTER = 0.6  # em: the widest gap between the letters of letter-spaced text (glyphs' boxes apart)
WORD = 1.5  # em: the widest gap between words on a line (poppler's too)
SPACED = 0.3  # em: lone letters in a row closer than this are a word's letters, spaced out
PARALLEL_PAGES = 64  # from this many pages, read by a process a core (see base.processes)
PAGES_PER_BATCH = 16
Z_PAGE, Z_DRAWING, Z_IMAGE, Z_TEXT = 0, 1, 2, 3
_WORD = re.compile(r"\S+")
_CAMEL = re.compile(r"[a-z][A-Z]")  # within an identifier: ConfigLoadAndParse
_HYPHENS = "-\u2010\u00ad\ufffe"  # a word broken at a line end ends with one of these
SOFT, MARK = "\u00ad", "\ufffe"  # the soft hyphen, and PDFium's mark of a line-end hyphen
LINE, SPACE = -1.0, -2.0  # a piece's gap when it starts a line, or lies apart from the one before
Box = tuple[float, float, float, float]


def detect(path: Path, head: bytes) -> bool:
    return b"%PDF-" in head[:1024] or path.suffix.lower() in SUFFIXES


def read(source: Source) -> Iterator[Batch]:
    """Batches of a few pages' items, made and checked where the pages are read: with many
    pages, by a process a core, so the file's pages are read in parallel."""
    import pypdfium2 as pdfium

    pdf = _open(source.path)
    try:
        count = len(pdf)
        places = _layout([pdf.get_page_size(i) for i in range(count)], max(1, source.columns))
        chunks = [range(s, min(s + PAGES_PER_BATCH, count)) for s in range(0, count, PAGES_PER_BATCH)]
        workers = processes()
        if count < PARALLEL_PAGES or workers < 2:
            made: Iterable[Batch] = (_batch(pdfium, pdf, r, places, source.max_data_bytes) for r in chunks)
            yield from _counted(made, chunks, source, count)
            return
        # PDFium is single-threaded: pages are read by processes, each with the file open once.
        context = multiprocessing.get_context("fork")
        with context.Pool(workers, _open_in_worker, (source.path, places, source.max_data_bytes)) as pool:
            yield from _counted(pool.imap(_batch_in_worker, chunks), chunks, source, count)
    finally:
        pdf.close()


def _counted(made: Iterable[Batch], chunks: list[range], source: Source, count: int) -> Iterator[Batch]:
    for pages, batch in zip(chunks, made, strict=False):
        source.done = source.size * pages.stop // count
        yield batch


def _open(path: Path):
    import pypdfium2 as pdfium

    try:
        return pdfium.PdfDocument(str(path))
    except pdfium.PdfiumError as error:
        fix = (
            "decrypt it first (qpdf --decrypt in.pdf out.pdf)"
            if "password" in str(error).lower()
            else "repair it (qpdf in.pdf out.pdf) or print it to a new PDF"
        )
        raise ImportFailed(f"PDFium cannot open it ({error}): {fix}") from None


def _layout(sizes: list[tuple[float, float]], columns: int) -> list[Box]:
    """Each page's place on the canvas (x0, y0, x1, y1): in ``columns``, rows as tall as their
    tallest page, each cell as wide as the widest."""
    cell = max((w for w, _ in sizes), default=0.0) + GAP
    places, top = [], 0.0
    for row in range(0, len(sizes), columns):
        for i, (w, h) in enumerate(sizes[row : row + columns]):
            places.append((i * cell, top, i * cell + w, top + h))
        top += max(h for _, h in sizes[row : row + columns]) + GAP
    return places


_worker: dict = {}


def _open_in_worker(path: Path, places: list[Box], max_data_bytes: int) -> None:
    import pypdfium2 as pdfium

    _worker.update(
        pdfium=pdfium, pdf=pdfium.PdfDocument(str(path)), places=places, max_data_bytes=max_data_bytes
    )


def _batch_in_worker(pages: range) -> Batch:
    return _batch(_worker["pdfium"], _worker["pdf"], pages, _worker["places"], _worker["max_data_bytes"])


def _batch(pdfium, pdf, pages: range, places: list[Box], max_data_bytes: int) -> Batch:
    """The items of ``pages``, checked as the server checks an import's.

    :raises ItemError: "page N: why"
    """
    items: list[Item] = []
    starts: list[int] = []
    for i in pages:
        starts.append(len(items))
        items.extend(Item(*record) for record in _page(pdfium, pdf, i, places[i]))
    return batch_of(items, max_data_bytes, lambda row: f"page {pages[bisect_right(starts, row) - 1] + 1}: ")


def _page(pdfium, pdf, i: int, place: Box) -> list[tuple]:
    """Page ``i``'s items as Item's fields (in a tuple: cheap to send between processes)."""
    import pypdfium2.raw as c

    number = i + 1
    ox, oy, x1, y1 = place
    out: list[tuple] = [(f"p{number}", ox, oy, x1, y1, "page", Z_PAGE, {"page": number})]
    page = pdf[i]
    try:
        put = _placer(page.get_cropbox(), page.get_rotation(), ox, oy)
        for k, box in enumerate(_objects(c, page.raw, c.FPDF_PAGEOBJ_IMAGE)):
            out.append((f"p{number}i{k}", *put(box), "image", Z_IMAGE))
        for k, box in enumerate(_objects(c, page.raw, c.FPDF_PAGEOBJ_PATH, c.FPDF_PAGEOBJ_SHADING)):
            out.append((f"p{number}d{k}", *put(box), "drawing", Z_DRAWING))
        text = c.FPDFText_LoadPage(page.raw)
        try:
            for k, (word, box, join) in enumerate(_words(c, text)):
                data = {"text": word, "join": join} if join else {"text": word}
                out.append((f"p{number}w{k}", *put(box), "text", Z_TEXT, data))
        finally:
            c.FPDFText_ClosePage(text)
    finally:
        page.close()
    return out


def _placer(crop: Box, rotation: int, ox: float, oy: float) -> Callable[[Box], Box]:
    """From a box in PDF space (left, bottom, right, top) to the page's place on the canvas."""
    left, bottom, right, top = crop
    if rotation == 90:  # the page turned clockwise: its left edge on top
        return lambda b: (ox + b[1] - bottom, oy + b[0] - left, ox + b[3] - bottom, oy + b[2] - left)
    if rotation == 180:
        return lambda b: (ox + right - b[2], oy + b[1] - bottom, ox + right - b[0], oy + b[3] - bottom)
    if rotation == 270:
        return lambda b: (ox + top - b[3], oy + right - b[2], ox + top - b[1], oy + right - b[0])
    return lambda b: (ox + b[0] - left, oy + top - b[3], ox + b[2] - left, oy + top - b[1])


def _words(c, text) -> list[tuple[str, Box, str | None]]:
    """The text page's words: each one's text, box (left, bottom, right, top) and how it
    joins the next (None, "word" or "hyphen": see the module's docstring)."""
    count = c.FPDFText_CountChars(text)
    if count <= 0:
        return []
    buffer = (ctypes.c_ushort * (count + 1))()
    written = c.FPDFText_GetText(text, 0, count, buffer)
    chars = bytes(buffer)[: 2 * max(written - 1, 0)].decode("utf-16-le", "replace")
    if len(chars) != count:  # characters beyond UTF-16's first plane, or without one: one at a time
        chars = "".join(map(partial(_char, c, text), range(count)))
    words: list[list] = []
    line: list[list] = []
    for piece in _pieces(c, text, chars):
        if piece[2] == LINE and line:
            words += _merged(c, text, line)
            line = []
        line.append(piece)
    words += _merged(c, text, line)
    for word in words:
        word[1] = _line_high(c, text, word)
    run: list[list] = []
    for word in words:  # runs of words side by side: a line as it shows (PDFium may break it)
        if run and not _beside(run[-1][1], word[1]):
            _even(run)
            run = []
        run.append(word)
    _even(run)
    return _joined(words, chars.lower())


def _beside(before: Box, box: Box) -> bool:
    """Whether ``box`` goes on the line ``before`` is on: right of it, their middles each
    within the other's height."""
    return (
        box[0] >= before[2]
        and before[1] < (box[1] + box[3]) / 2 < before[3]
        and box[1] < (before[1] + before[3]) / 2 < box[3]
    )


def _even(line: list[list]) -> None:
    """Words side by side made as tall as their line (the union of their heights): a code
    word or a bullet in a smaller font is as tall as the prose around it, so a page that draws
    text by its height draws the whole line as text, or the whole line as bars."""
    if len(line) < 2:
        return
    y0, y1 = min(word[1][1] for word in line), max(word[1][3] for word in line)
    for word in line:
        word[1] = (word[1][0], y0, word[1][2], y1)


def _line_high(c, text, word: list) -> Box:
    """``word``'s box grown to its font's line: from the font's descent to its ascent, as
    PDFium's loose boxes of its first and last characters give them. Glyph-tight boxes would
    make ``ace`` shorter than ``The`` on one line; a line's words in one font at one size are as
    tall as one another, so a page draws all or none of them as text at a given zoom."""
    x0, y0, x1, y1 = word[1]
    loose = c.FS_RECTF()
    for k in (word[3], word[4]):
        if c.FPDFText_GetLooseCharBox(text, k, ctypes.byref(loose)) and loose.top > loose.bottom:
            x0, y0 = min(x0, loose.left), min(y0, loose.bottom)
            x1, y1 = max(x1, loose.right), max(y1, loose.top)
    return (x0, y0, x1, y1)


def _char(c, text, i: int) -> str:
    """Character ``i`` of the text page as ``FPDFText_GetText`` gives it: PDFium's mark where a
    line-end hyphen is (whatever the font's code for it), a space where there is none."""
    code = c.FPDFText_GetUnicode(text, i)
    if (code < 0x20 or chr(code) in _HYPHENS) and code not in (10, 13) and c.FPDFText_IsHyphen(text, i):
        return MARK
    return chr(code or 32)


def _pieces(c, text, chars: str) -> list[list]:
    """``[text, box, gap, first, last, after]`` for each run of characters between whitespace:
    ``gap`` is LINE after a line break (or first), SPACE from a piece not beside it on the
    line, else the gap from the piece before, in em of the line's first character's font;
    ``first``, ``last``: the indices of its first and last characters; ``after``: of the
    first of the whitespace before it. A run holding PDFium's line-end hyphen mark is two
    pieces, each on its line."""
    left, top, right, bottom = (ctypes.c_double() for _ in range(4))
    refs = ctypes.byref(left), ctypes.byref(top), ctypes.byref(right), ctypes.byref(bottom)
    count_rects, get_rect, font_size = c.FPDFText_CountRects, c.FPDFText_GetRect, c.FPDFText_GetFontSize
    out: list[list] = []
    end, size, box = 0, 0.0, (0.0, 0.0, 0.0, 0.0)
    for match in _WORD.finditer(chars):
        start, word = match.start(), match.group()
        gap = chars[end:start]
        new_line = not out or "\n" in gap or "\r" in gap
        after, end = end, match.end()
        cuts = [(start, end)]
        if MARK in word[:-1]:
            ends = [start + k + 1 for k, ch in enumerate(word[:-1]) if ch == MARK]
            cuts = list(zip([start, *ends], [*ends, end], strict=True))
        for a, b in cuts:
            rects = count_rects(text, a, b - a)
            if rects <= 0:
                continue
            get_rect(text, 0, *refs)
            x0, y0, x1, y1 = left.value, bottom.value, right.value, top.value
            for j in range(1, rects):
                get_rect(text, j, *refs)
                x0, y0 = min(x0, left.value), min(y0, bottom.value)
                x1, y1 = max(x1, right.value), max(y1, top.value)
            if new_line:
                size, gap_em = font_size(text, a) or y1 - y0, LINE
            elif x0 >= box[0] and box[1] < (y0 + y1) / 2 < box[3] and size > 0:  # beside: on its line
                gap_em = (x0 - box[2]) / size if x0 > box[2] else 0.0
            else:
                gap_em = SPACE
            box = (x0, y0, x1, y1)
            out.append([word if b - a == len(word) else chars[a:b], box, gap_em, a, b - 1, after])
            new_line = True  # the piece after a line-end hyphen's mark starts the next line
    return out


def _made_up(c, text, piece: list) -> bool:
    """Whether the whitespace before ``piece`` is all PDFium's, not the PDF's."""
    return all(c.FPDFText_IsGenerated(text, k) for k in range(piece[5], piece[3]))


def _merged(c, text, line: list[list]) -> list[list]:
    """A line's pieces with those of one word joined: across a made-up space narrower than
    KERN em, or, on a line of letter-spaced text, one as narrow as its letters' gaps."""
    if len(line) < 2:
        return line
    widest = _letter_gap(c, text, line)
    if not any(p[2] >= 0 and (p[2] < KERN or p[2] <= widest) for p in line):
        return line  # most lines: nothing to join
    out = [list(line[0])]
    for piece in line[1:]:
        word, gap = out[-1], piece[2]
        if gap >= 0 and (gap < KERN or gap <= widest) and _made_up(c, text, piece):
            a, b = word[1], piece[1]
            word[0] += piece[0]
            word[1] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
            word[4] = piece[4]
        else:
            out.append(list(piece))
    return out


def _letter_gap(c, text, line: list[list]) -> float:
    """The widest gap between letters, in em, if ``line`` holds letter-spaced text; else -1.

    PDFium makes up spaces between some letters of letter-spaced text, leaving letters alone
    (``Ch an geS t a r tin gV alue``, ``v oid``, ``s i z e o f``: a code listing's columns;
    ``S P A C E D`` out). A line shows it: three lone letters or digits in a row a made-up
    space apart, or a lone one beside a short word whose own letters lie apart (``oid``;
    ``in`` beside ``a`` is set tight), closer than SPACED em. Then its gaps, between pieces and
    within those words, come in sizes, the letters' the narrowest, then the words' (then a
    line number's, a column's...): the letters' are those below the first jump between two
    (1.25x and 0.1 em at least), if none is wider than LETTER em, the gap above the jump is a
    word's (WORD em at most), and the gaps that showed it lie below: ``d p q a b c``, names
    a word space apart, are words."""
    lone = [len(p[0]) == 1 and p[0].isalnum() for p in line]
    if not any(lone):
        return -1.0
    near = [KERN <= p[2] < SPACED for p in line[1:]]  # line[k] to line[k + 1]; made up: checked below
    run = {
        j
        for k in range(len(line) - 2)
        if lone[k] and lone[k + 1] and lone[k + 2] and near[k] and near[k + 1]
        for j in (k + 1, k + 2)
    }
    beside = {
        id(line[j]): (line[j], line[k + 1])
        for k, close in enumerate(near)
        if close and lone[k] != lone[k + 1]
        for j in (k, k + 1)
        if not lone[j] and 1 < len(line[j][0]) <= 4 and line[j][0].isalpha()
    }
    if not run and not beside:
        return -1.0  # most lines: no lone letter a letter's gap from another, or from a short word
    shown = [
        line[j][2]
        for j in run
        if _made_up(c, text, line[j]) and _gap_in_own_em(c, text, line[j - 1], line[j]) < SPACED
    ]
    inner = [
        gaps
        for piece, after in beside.values()
        if _made_up(c, text, after) and min(gaps := _inner_gaps(c, text, piece)) >= KERN
    ]
    shown += [g for gaps in inner for g in gaps]
    if not shown:
        return -1.0
    sizes = sorted([p[2] for p in line[1:] if p[2] >= KERN] + [g for gaps in inner for g in gaps])
    jumps = [k for k, (a, b) in enumerate(itertools.pairwise(sizes)) if b >= 1.25 * a and b - a >= 0.1]
    if not jumps:
        return -1.0  # gaps of one size only
    widest, above = sizes[jumps[0]], sizes[jumps[0] + 1]  # the letters' gaps are the narrowest
    return widest if widest <= LETTER and above <= WORD and max(shown) <= widest else -1.0


def _gap_in_own_em(c, text, before: list, piece: list) -> float:
    """The gap between two pieces in em of the font of the one before."""
    size = c.FPDFText_GetFontSize(text, before[4])
    return (piece[1][0] - before[1][2]) / size if size > 0 else LETTER


def _inner_gaps(c, text, piece: list) -> list[float]:
    """The gaps between the characters of ``piece``, in em (of the font's size)."""
    left, right, bottom, top = (ctypes.c_double() for _ in range(4))
    refs = ctypes.byref(left), ctypes.byref(right), ctypes.byref(bottom), ctypes.byref(top)
    first, last = piece[3], piece[4]
    size = c.FPDFText_GetFontSize(text, first)
    if size <= 0:
        return [0.0]
    gaps: list[float] = []
    c.FPDFText_GetCharBox(text, first, *refs)
    end = right.value
    for k in range(first + 1, last + 1):
        c.FPDFText_GetCharBox(text, k, *refs)
        gaps.append(max(0.0, left.value - end) / size)
        end = right.value
    return gaps


def _joined(words: list[list], page: str) -> list[tuple[str, Box, str | None]]:
    """The page's words, each with how it joins the next: "hyphen" or "word" where it ends a
    line with a hyphen and the next line goes on with the word (see the module's docstring);
    soft hyphens and PDFium's marks of a line-end hyphen shown as the hyphens they are."""
    out: list[tuple[str, Box, str | None]] = []
    for k, (word, box, *_) in enumerate(words):
        if word[-1] not in _HYPHENS and SOFT not in word and MARK not in word:  # most words
            out.append((word[:MAX_WORD], box, None))
            continue
        join = None
        if k + 1 < len(words) and words[k + 1][2] == LINE and _broken(word, words[k + 1][0]):
            after = words[k + 1]
            if after[1][3] <= box[3] or after[1][0] >= box[2]:  # on the next line, or column
                join = _join(word, after[0], page)
        if word[-1] in (SOFT, MARK):
            word = word[:-1] + "-"
        word = word.replace(SOFT, "").replace(MARK, "-")
        if word:
            out.append((word[:MAX_WORD], box, join if len(word) <= MAX_WORD else None))
    return out


def _broken(word: str, after: str) -> bool:
    """Whether ``word`` ends with a hyphen that may break it, with a letter or digit before it,
    and ``after`` begins with one."""
    return len(word) > 1 and word[-1] in _HYPHENS and word[-2].isalnum() and after[:1].isalnum()


def _join(word: str, after: str, page: str) -> str:
    """How ``word``, which ends a line with a hyphen, joins ``after``, which begins the next:
    "hyphen" for a hyphen that only breaks the word, "word" for one that belongs to it."""
    if word[-1] == SOFT:  # PDFium's mark hides a soft hyphen it found: decided as a hyphen's
        return "hyphen"
    head, tail = re.search(r"\w+$", word[:-1]), re.match(r"\w+", after)
    if head and tail:  # the page spells it elsewhere: object-oriented; MulByPowD
        spelt = re.compile(rf"\b{re.escape(head.group().lower())}(-?){re.escape(tail.group().lower())}\b")
        hyphens = {m.group(1) for m in spelt.finditer(page)}
        if len(hyphens) == 1:
            return "word" if hyphens == {"-"} else "hyphen"
    # As PDF.js reads it: broken between lowercase letters (or in an identifier: Fc-ConfigLoad);
    # else 2008-02, X-Window, non-English: digits, or a capital on either side
    if word[-2].islower() and (after[0].islower() or (tail and _CAMEL.search(tail.group()))):
        return "hyphen"
    # an identifier's humps broken beside a capital, as LibreOffice hyphenates them:
    # ChangeStarting-Value, ChangeS-tartingValue
    if head and _CAMEL.search(head.group()) and (after[0].isupper() or word[-2].isupper()):
        return "hyphen"
    return "word"


def _objects(c, page, *kinds: int) -> Iterator[Box]:
    """The boxes (left, bottom, right, top, on the page) of the page's objects of ``kinds``, in
    form XObjects too; paths that neither fill nor stroke (clipping helpers) left out."""
    left, bottom, right, top = (ctypes.c_float() for _ in range(4))
    refs = ctypes.byref(left), ctypes.byref(bottom), ctypes.byref(right), ctypes.byref(top)
    fill, stroke = ctypes.c_int(), ctypes.c_int()
    modes = ctypes.byref(fill), ctypes.byref(stroke)

    def walk(count: int, get: Callable, matrix: tuple | None) -> Iterator[Box]:
        for j in range(count):
            obj = get(j)
            kind = c.FPDFPageObj_GetType(obj)
            if kind == c.FPDF_PAGEOBJ_FORM:
                m = c.FS_MATRIX()
                if c.FPDFPageObj_GetMatrix(obj, ctypes.byref(m)):
                    inner = (m.a, m.b, m.c, m.d, m.e, m.f)
                    yield from walk(
                        c.FPDFFormObj_CountObjects(obj),
                        lambda k, form=obj: c.FPDFFormObj_GetObject(form, k),
                        inner if matrix is None else compose(matrix, inner),
                    )
                continue
            if kind not in kinds or not c.FPDFPageObj_GetBounds(obj, *refs):
                continue
            paints = kind == c.FPDF_PAGEOBJ_PATH and c.FPDFPath_GetDrawMode(obj, *modes)
            if paints and not fill.value and not stroke.value:
                continue
            box = (left.value, bottom.value, right.value, top.value)
            yield box if matrix is None else _transformed(matrix, box)

    yield from walk(c.FPDFPage_CountObjects(page), lambda k: c.FPDFPage_GetObject(page, k), None)


def _transformed(m: Matrix, box: Box) -> Box:
    """The axis-aligned box around ``box`` transformed by ``m``."""
    x0, y0, x1, y1 = box
    return bounds(apply(m, corner) for corner in ((x0, y0), (x1, y0), (x1, y1), (x0, y1)))
