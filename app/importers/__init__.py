"""Files in, items out: one module a format, one interface, one registry choosing by content.

Each format module has ``NAME``, ``SUFFIXES``, ``detect(path, head) -> bool`` (``head``: the
file's first bytes) and ``read(source) -> Iterator[(where, item)]``, where ``item`` is an
:class:`~app.items.Item` or a dict of its fields and ``where`` names the record for an error
("row 7", "element 3 (id 'a1')"); a module may yield whole batches it made and checked
itself (``batch_of``) instead, as PDF's worker processes do. ``read`` advances
``source.done`` (bytes read) for the progress bar. :func:`batches` turns records into the
same validated batches the server's import decodes, so a file is checked by the same rules,
and named by its lines or rows, before anything is stored or sent.

A gzipped file of any format is found by its magic bytes, whatever its name, and its format
by what it holds: NDJSON is read as a stream, any other format from a copy decompressed
into the import's scratch directory (beside the store's snapshot files), removed once read.
A file in no format says what it looks like and what to do with it.

>>> [f.NAME for f in FORMATS]
['NDJSON', 'PDF', 'Excalidraw', 'tldraw', 'JSON array', 'CSV']
"""

from __future__ import annotations

import gzip
import os
import shutil
import tempfile
import zlib
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

import msgspec

from ..items import Batch, Columns, Item, ItemError, batch_of
from . import csv_table, excalidraw, json_array, ndjson, pdf, tldraw
from .base import ImportFailed, Source

__all__ = ["FORMATS", "ImportFailed", "Source", "batches", "detect"]

# Content first (magic bytes, a format's own marker); the loosest guesses last.
FORMATS: list[ModuleType] = [ndjson, pdf, excalidraw, tldraw, json_array, csv_table]
HEAD_BYTES = 4096
RECORDS_PER_BATCH = 16_384


GZIP = ndjson.GZIP


def detect(path: Path) -> ModuleType:
    """The format module that reads ``path``, gzipped or not (by its first bytes).

    :raises ImportFailed: if no format recognises it (saying what it looks like and what to
        do), or it is a gzip file cut short or damaged
    """
    try:
        with path.open("rb") as file:
            head = file.read(HEAD_BYTES)
            zipped = head.startswith(GZIP)
            if zipped:
                file.seek(0)
                head = _head_of(gzip.GzipFile(fileobj=file, mode="rb"), path)
    except OSError as error:
        raise ImportFailed(f"{path}: cannot read it ({error.strerror or error})") from None
    named = path.with_name(_unzipped_name(path.name)) if zipped else path
    for module in FORMATS:
        if module.detect(named, head):
            return module
    what, fix = _looks_like(head)
    names = ", ".join(f"{m.NAME} ({' '.join(m.SUFFIXES)})" for m in FORMATS)
    raise ImportFailed(
        f"{path}: not a format vantage import reads: {'a gzip file holding ' if zipped else ''}{what}; "
        f"{fix}. It reads {names}, gzipped too."
    )


def _head_of(body: gzip.GzipFile, path: Path) -> bytes:
    """The first bytes a gzip file holds.

    :raises ImportFailed: if it is cut short or damaged before them
    """
    try:
        return body.read(HEAD_BYTES)
    except (EOFError, zlib.error, gzip.BadGzipFile) as error:
        raise ImportFailed(f"{path}: {_damaged(error)}") from None


def _damaged(error: BaseException) -> str:
    return (
        f"not a whole gzip file ({error or 'cut short'}): test it with gunzip -t, which names the "
        "damage, or download or export it again"
    )


def _unzipped_name(name: str) -> str:
    """A gzipped file's name without its ``.gz`` (``report.pdf.gz``: ``report.pdf``)."""
    stem = name[:-3] if name.lower().endswith(".gz") else name
    return stem or "unzipped"


_CONVERT = (
    'convert it to NDJSON, one item a line: {"id": "a", "x0": 0, "y0": 0, "x1": 10, "y1": 10, "kind": "box"}'
)


def _looks_like(head: bytes) -> tuple[str, str]:
    """What a file in no format vantage import reads looks like, from its first bytes, and what
    to do with it.

    >>> _looks_like(b"PK\\x03\\x04" + b"[Content_Types].xml xl/workbook.xml")
    ('an Excel workbook (.xlsx)', 'save its sheet as CSV with a header id,x0,y0,x1,y1')
    >>> _looks_like(b"just some words")[0]
    'plain text, not CSV with a header id,x0,y0,x1,y1'
    """
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    lower = text[:512].lower()
    if not head:
        return "an empty file", "there is nothing in it to import"
    if head.startswith(b"PK\x03\x04"):
        if b"xl/" in head:
            return "an Excel workbook (.xlsx)", "save its sheet as CSV with a header id,x0,y0,x1,y1"
        if b"word/" in head:
            return "a Word document (.docx)", "export it as PDF (File > Export) and import the PDF"
        if b"opendocument.spreadsheet" in head:
            return "an OpenDocument spreadsheet (.ods)", "save its sheet as CSV with a header id,x0,y0,x1,y1"
        if b"opendocument" in head:
            return "an OpenDocument file", "export it as PDF and import the PDF"
        return "a ZIP archive", "unzip it and import the files in it"
    for magic, what, tool in (
        (b"BZh", "bzip2", "bunzip2"),
        (b"\xfd7zXZ\x00", "xz", "unxz"),
        (b"\x28\xb5\x2f\xfd", "zstd", "unzstd"),
        (b"7z\xbc\xaf\x27\x1c", "7-Zip", "7z x"),
    ):
        if head.startswith(magic):
            return f"compressed with {what}", f"decompress it ({tool}) and import what it holds"
    if head[257:262] == b"ustar":
        return "a tar archive", "extract it (tar -xf) and import the files in it"
    for magic, what in (
        (b"\x89PNG", "a PNG image"),
        (b"\xff\xd8\xff", "a JPEG image"),
        (b"GIF8", "a GIF image"),
        (b"II*\x00", "a TIFF image"),
        (b"MM\x00*", "a TIFF image"),
        (b"BM", "a BMP image"),
    ):
        if head.startswith(magic):
            return what, "put it in a PDF (img2pdf, or print it to PDF) to import it as a page with an image"
    if head.startswith(b"RIFF") and head[8:12] == b"WEBP":
        return "a WebP image", "put it in a PDF (print it to PDF) to import it as a page with an image"
    if head.startswith(b"%!PS"):
        return "PostScript", "convert it to PDF (ps2pdf in.ps out.pdf) and import the PDF"
    if head.startswith((b"\xff\xfe", b"\xfe\xff")):
        return "text in UTF-16", "save it as UTF-8 (iconv -f UTF-16 -t UTF-8)"
    if lower.startswith((b"<!doctype html", b"<html")) or b"<html" in lower:
        return (
            "an HTML page",
            "a download may have saved the page around the file, not the file: download it again",
        )
    if lower.startswith(b"<svg") or (lower.startswith(b"<?xml") and b"<svg" in lower):
        return "an SVG drawing", "export it as PDF and import the PDF"
    if lower.startswith(b"<?xml") or lower.startswith(b"<"):
        return "XML", _CONVERT
    if text.startswith(b"{"):
        return "JSON, but not an item a line, an Excalidraw scene or a tldraw file", _CONVERT
    if b"\x00" in head:
        return "binary data", _CONVERT
    return "plain text, not CSV with a header id,x0,y0,x1,y1", _CONVERT


def batches(
    source: Source, module: ModuleType, max_line_bytes: int, max_data_bytes: int
) -> Iterator[Batch | Columns]:
    """The file's items as validated batches (an NDJSON file decoded as the server decodes it;
    a big one comes packed, as ``Columns``).

    :raises ImportFailed: naming the file and the record, for the first bad one
    """
    try:
        if module is ndjson:
            yield from ndjson.batches(source, max_line_bytes, max_data_bytes)
        else:
            source.max_data_bytes = max_data_bytes
            with _unzipped(source) as plain:
                for batch in _batched(module.read(plain), max_data_bytes):
                    source.done = source.size * plain.done // max(plain.size, 1)
                    yield batch
    except (ItemError, ImportFailed) as error:
        raise ImportFailed(f"{source.path}: {error}") from None


@contextmanager
def _unzipped(source: Source) -> Iterator[Source]:
    """``source``, or if it is gzipped, a copy decompressed into its scratch directory (the
    system's temporary one without), removed when done: a hidden ``.tmp`` file, which a
    server's sweep removes if a killed import left it.

    :raises ImportFailed: if it is cut short or damaged, or the copy cannot be written
    """
    with source.path.open("rb") as file:
        if file.read(2) != GZIP:
            yield source
            return
        file.seek(0)
        if source.scratch is not None:
            source.scratch.mkdir(parents=True, exist_ok=True)
        handle, name = tempfile.mkstemp(prefix=".gunzipped-", suffix=".tmp", dir=source.scratch)
        plain = Path(name)
        try:
            try:
                with gzip.GzipFile(fileobj=file, mode="rb") as body, os.fdopen(handle, "wb") as out:
                    shutil.copyfileobj(body, out, 1 << 20)
            except (EOFError, zlib.error, gzip.BadGzipFile) as error:
                raise ImportFailed(_damaged(error)) from None
            except OSError as error:
                raise ImportFailed(
                    f"cannot decompress it into {plain.parent} ({error.strerror or error}): free some "
                    "space, or decompress it yourself (gunzip -k) and import that"
                ) from None
            yield Source(
                plain,
                plain.stat().st_size,
                columns=source.columns,
                max_data_bytes=source.max_data_bytes,
                scratch=source.scratch,
            )
        finally:
            plain.unlink(missing_ok=True)


def _batched(records: Iterable[tuple[str, Item | dict] | Batch], max_data_bytes: int) -> Iterator[Batch]:
    items: list[Item] = []
    wheres: list[str] = []
    for record in records:
        if isinstance(record, Batch):  # made and checked by the format module (PDF pages)
            if items:
                yield batch_of(items, max_data_bytes, lambda row: f"{wheres[row]}: ")
                items, wheres = [], []
            yield record
            continue
        where, given = record
        if isinstance(given, Item):
            items.append(given)
        else:
            try:
                items.append(msgspec.convert(given, Item))
            except msgspec.ValidationError as error:
                raise ItemError(f"{where}: {error}") from None
        wheres.append(where)
        if len(items) == RECORDS_PER_BATCH:
            yield batch_of(items, max_data_bytes, lambda row: f"{wheres[row]}: ")
            items, wheres = [], []
    if items:
        yield batch_of(items, max_data_bytes, lambda row: f"{wheres[row]}: ")
