"""PDF pages as canvas items, read with pypdfium2 (PDFium): each page's frame (kind "page"),
its words (kind "text", the word in ``data``), images (kind "image") and drawings (kind
"drawing": paths and shadings that paint something). Pages are stacked top to bottom with a
gap, or laid out in ``columns`` side by side (left to right, then down), in points; PDF's y,
which grows upward from the page's bottom, is flipped so it grows downward like the canvas's,
and a page's /Rotate is applied as a viewer shows it.

Words are PDFium's characters split at whitespace (PDFium puts a space or a line break where
the layout has a gap); a word's box is the union of its characters' boxes.
"""

from __future__ import annotations

import ctypes
import re
from collections.abc import Callable, Iterator
from pathlib import Path

from ..items import Item
from .base import ImportFailed, Source

NAME = "PDF"
SUFFIXES = (".pdf",)
GAP = 24.0  # points between pages
MAX_WORD = 900  # characters of a word kept in its data (a PDF may hold a "word" of megabytes)
Z_PAGE, Z_DRAWING, Z_IMAGE, Z_TEXT = 0, 1, 2, 3
_WORD = re.compile(r"\S+")
Box = tuple[float, float, float, float]


def detect(path: Path, head: bytes) -> bool:
    return b"%PDF-" in head[:1024] or path.suffix.lower() in SUFFIXES


def read(source: Source) -> Iterator[tuple[str, Item]]:
    import pypdfium2 as pdfium

    try:
        pdf = pdfium.PdfDocument(str(source.path))
    except pdfium.PdfiumError as error:
        fix = (
            "decrypt it first (qpdf --decrypt in.pdf out.pdf)"
            if "password" in str(error).lower()
            else "repair it (qpdf in.pdf out.pdf) or print it to a new PDF"
        )
        raise ImportFailed(f"PDFium cannot open it ({error}): {fix}") from None
    try:
        yield from _pages(pdf, source)
    finally:
        pdf.close()


def _pages(pdf, source: Source) -> Iterator[tuple[str, Item]]:
    import pypdfium2.raw as c

    count = len(pdf)
    sizes = [pdf.get_page_size(i) for i in range(count)]  # as shown: /Rotate applied
    columns = max(1, source.columns)
    cell_width = max((w for w, _ in sizes), default=0.0) + GAP
    tops, top = [], 0.0
    for row in range(0, count, columns):
        tops.append(top)
        top += max(h for _, h in sizes[row : row + columns]) + GAP
    for i in range(count):
        number, where = i + 1, f"page {i + 1}"
        ox, oy = (i % columns) * cell_width, tops[i // columns]
        w, h = sizes[i]
        yield where, Item(f"p{number}", ox, oy, ox + w, oy + h, "page", Z_PAGE, {"page": number})
        page = pdf[i]
        try:
            place = _placer(page.get_cropbox(), page.get_rotation(), ox, oy)
            for k, box in enumerate(_objects(c, page.raw, c.FPDF_PAGEOBJ_IMAGE)):
                yield where, Item(f"p{number}i{k}", *place(box), "image", Z_IMAGE)
            for k, box in enumerate(_objects(c, page.raw, c.FPDF_PAGEOBJ_PATH, c.FPDF_PAGEOBJ_SHADING)):
                yield where, Item(f"p{number}d{k}", *place(box), "drawing", Z_DRAWING)
            text = c.FPDFText_LoadPage(page.raw)
            try:
                for k, (word, box) in enumerate(_words(c, text)):
                    yield where, Item(f"p{number}w{k}", *place(box), "text", Z_TEXT, {"text": word})
            finally:
                c.FPDFText_ClosePage(text)
        finally:
            page.close()
        source.done = source.size * number // count


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


def _words(c, text) -> Iterator[tuple[str, Box]]:
    """The text page's words and their boxes (left, bottom, right, top)."""
    count = c.FPDFText_CountChars(text)
    if count <= 0:
        return
    buffer = (ctypes.c_ushort * (count + 1))()
    written = c.FPDFText_GetText(text, 0, count, buffer)
    chars = bytes(buffer)[: 2 * max(written - 1, 0)].decode("utf-16-le", "replace")
    if len(chars) != count:  # characters beyond UTF-16's first plane: one at a time
        chars = "".join(chr(c.FPDFText_GetUnicode(text, i) or 32) for i in range(count))
    l, t, r, b = (ctypes.c_double() for _ in range(4))
    refs = ctypes.byref(l), ctypes.byref(t), ctypes.byref(r), ctypes.byref(b)
    count_rects, get_rect = c.FPDFText_CountRects, c.FPDFText_GetRect
    for match in _WORD.finditer(chars):
        start = match.start()
        rects = count_rects(text, start, match.end() - start)
        if rects <= 0:
            continue
        get_rect(text, 0, *refs)
        x0, y0, x1, y1 = l.value, b.value, r.value, t.value
        for j in range(1, rects):
            get_rect(text, j, *refs)
            x0, y0, x1, y1 = min(x0, l.value), min(y0, b.value), max(x1, r.value), max(y1, t.value)
        yield match.group()[:MAX_WORD], (x0, y0, x1, y1)


def _objects(c, page, *kinds: int) -> Iterator[Box]:
    """The boxes (left, bottom, right, top, on the page) of the page's objects of ``kinds``, in
    form XObjects too; paths that neither fill nor stroke (clipping helpers) left out."""
    l, b, r, t = (ctypes.c_float() for _ in range(4))
    refs = ctypes.byref(l), ctypes.byref(b), ctypes.byref(r), ctypes.byref(t)
    fill, stroke = ctypes.c_int(), ctypes.c_int()

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
                        inner if matrix is None else _times(matrix, inner),
                    )
                continue
            if kind not in kinds or not c.FPDFPageObj_GetBounds(obj, *refs):
                continue
            if kind == c.FPDF_PAGEOBJ_PATH and c.FPDFPath_GetDrawMode(
                obj, ctypes.byref(fill), ctypes.byref(stroke)
            ):
                if not fill.value and not stroke.value:
                    continue
            box = (l.value, b.value, r.value, t.value)
            yield box if matrix is None else _transformed(matrix, box)

    yield from walk(c.FPDFPage_CountObjects(page), lambda k: c.FPDFPage_GetObject(page, k), None)


def _times(m: tuple, n: tuple) -> tuple:
    """``n`` then ``m`` (PDF matrices a b c d e f: x' = a x + c y + e)."""
    a, b, c, d, e, f = m
    a2, b2, c2, d2, e2, f2 = n
    return (
        a2 * a + b2 * c,
        a2 * b + b2 * d,
        c2 * a + d2 * c,
        c2 * b + d2 * d,
        e2 * a + f2 * c + e,
        e2 * b + f2 * d + f,
    )


def _transformed(m: tuple, box: Box) -> Box:
    a, b, c, d, e, f = m
    xs, ys = [], []
    for x, y in ((box[0], box[1]), (box[2], box[1]), (box[2], box[3]), (box[0], box[3])):
        xs.append(a * x + c * y + e)
        ys.append(b * x + d * y + f)
    return min(xs), min(ys), max(xs), max(ys)
