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
import multiprocessing
import re
from bisect import bisect_right
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from ..items import Batch, Item, batch_of
from .base import ImportFailed, Matrix, Source, apply, bounds, compose, processes

NAME = "PDF"
SUFFIXES = (".pdf",)
GAP = 24.0  # points between pages
MAX_WORD = 900  # characters of a word kept in its data (a PDF may hold a "word" of megabytes)
PARALLEL_PAGES = 64  # from this many pages, read by a process a core (see base.processes)
PAGES_PER_BATCH = 16
Z_PAGE, Z_DRAWING, Z_IMAGE, Z_TEXT = 0, 1, 2, 3
_WORD = re.compile(r"\S+")
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
            for k, (word, box) in enumerate(_words(c, text)):
                out.append((f"p{number}w{k}", *put(box), "text", Z_TEXT, {"text": word}))
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
    left, top, right, bottom = (ctypes.c_double() for _ in range(4))
    refs = ctypes.byref(left), ctypes.byref(top), ctypes.byref(right), ctypes.byref(bottom)
    count_rects, get_rect = c.FPDFText_CountRects, c.FPDFText_GetRect
    for match in _WORD.finditer(chars):
        start = match.start()
        rects = count_rects(text, start, match.end() - start)
        if rects <= 0:
            continue
        get_rect(text, 0, *refs)
        x0, y0, x1, y1 = left.value, bottom.value, right.value, top.value
        for j in range(1, rects):
            get_rect(text, j, *refs)
            x0, y0 = min(x0, left.value), min(y0, bottom.value)
            x1, y1 = max(x1, right.value), max(y1, top.value)
        yield match.group()[:MAX_WORD], (x0, y0, x1, y1)


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
