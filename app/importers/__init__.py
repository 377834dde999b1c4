"""Files in, items out: one module a format, one interface, one registry choosing by content.

Each format module has ``NAME``, ``SUFFIXES``, ``detect(path, head) -> bool`` (``head``: the
file's first bytes) and ``read(source) -> Iterator[(where, item)]``, where ``item`` is an
:class:`~app.items.Item` or a dict of its fields and ``where`` names the record for an error
("row 7", "element 3 (id 'a1')"); a module may yield whole batches it made and checked
itself (``batch_of``) instead, as PDF's worker processes do. ``read`` advances
``source.done`` (bytes read) for the progress bar. :func:`batches` turns records into the
same validated batches the server's import decodes, so a file is checked by the same rules,
and named by its lines or rows, before anything is stored or sent.

>>> [f.NAME for f in FORMATS]
['NDJSON', 'PDF', 'Excalidraw', 'tldraw', 'JSON array', 'CSV']
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
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


def detect(path: Path) -> ModuleType:
    """The format module that reads ``path``.

    :raises ImportFailed: if no format recognises it
    """
    try:
        with path.open("rb") as file:
            head = file.read(HEAD_BYTES)
    except OSError as error:
        raise ImportFailed(f"{path}: cannot read it ({error.strerror or error})") from None
    for module in FORMATS:
        if module.detect(path, head):
            return module
    names = ", ".join(f"{m.NAME} ({' '.join(m.SUFFIXES)})" for m in FORMATS)
    raise ImportFailed(
        f"{path}: not a format vantage import reads; it reads {names}. Convert it to NDJSON, "
        'one item a line: {"id": "a", "x0": 0, "y0": 0, "x1": 10, "y1": 10, "kind": "box"}'
    )


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
            yield from _batched(module.read(source), max_data_bytes)
    except (ItemError, ImportFailed) as error:
        raise ImportFailed(f"{source.path}: {error}") from None


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
