"""Canvas items on the wire: what clients send, checked in compiled code, and the JSON sent back.

An import decodes NDJSON in batches of lines with msgspec (typed, in C: ~1 us an item) into
columns: ids, an (n, 4) box array and each item's response JSON. A single-item edit goes
through the same type, so both paths accept and refuse exactly the same items.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from operator import attrgetter
from typing import Annotated, Any, Protocol, TypeVar

import msgspec
import numpy as np
from msgspec import UNSET, Meta, Struct, UnsetType

from spatial.rect import first_bad_box

from .errors import Invalid
from .looks import AGG_PREFIX

__all__ = [
    "Batch",
    "Columns",
    "Item",
    "ItemError",
    "batch_of",
    "boxes_of",
    "columns_of",
    "decode_item",
    "decode_json_array",
    "decode_ndjson",
    "ndjson_block",
    "ndjson_blocks",
    "newlines_in",
]

LINES_PER_BATCH = 16_384
BLOCK_BYTES = 1 << 20  # bytes of an NDJSON body read at a time
_ITEM_LINE = re.compile(rb"\S[^\n]*")  # a line's text from its first non-blank byte: blank lines hold none
_BLANK_LINE, _BLANK_FIRST = re.compile(rb"\n\s*?\n"), re.compile(rb"\s*?\n")  # \s as ``_ITEM_LINE``'s \S
_SPACE = np.zeros(256, bool)
_SPACE[list(b" \t\n\r\f\v")] = True  # the bytes \s matches
MAX_DATA_DEPTH = 32  # levels of nesting in an item's ``data``
_UNREADABLE = (msgspec.DecodeError, UnicodeDecodeError, RecursionError)  # what a bad body can raise


class Readable(Protocol):
    """What a body is read from: a file, a spooled upload, a gzip stream."""

    def read(self, size: int = -1, /) -> bytes: ...


class Item(Struct, forbid_unknown_fields=True, gc=False):
    """One item as clients send it and as responses carry it (``data`` only when set).

    Not tracked by Python's cycle collector (``gc=False``): an item holds strings, numbers and
    JSON's dicts and lists, never a cycle, and a block's 16k items tracked made the collector
    run over them as they were made (decoding and checking a block took 0.83x the CPU without).
    """

    id: Annotated[str, Meta(min_length=1, max_length=256)]
    x0: float
    y0: float
    x1: float
    y1: float
    kind: Annotated[str, Meta(min_length=1, max_length=32)] = "box"
    z: Annotated[int, Meta(ge=-(2**31), lt=2**31)] = 0
    data: dict[str, Any] | UnsetType = UNSET


class ItemError(Invalid):
    """An item a client sent is invalid; the message says where and why."""


@dataclass(frozen=True)
class Batch:
    """Validated items as columns, in the order they came."""

    ids: list[str]
    boxes: np.ndarray  # (n, 4) float64
    bodies: list[bytes]  # each item's response JSON

    def __len__(self) -> int:
        return len(self.ids)

    def columns(self) -> Columns:
        lengths = np.fromiter(map(len, self.bodies), np.int64, len(self.bodies))
        return Columns(*_lines_packed(self.ids), self.boxes, b"".join(self.bodies), np.cumsum(lengths))

    def lines(self) -> bytes:
        """The items as NDJSON lines, each ending in a newline."""
        return b"\n".join(self.bodies) + b"\n"


@dataclass(frozen=True)
class Columns:
    """Validated items packed for storing: their JSON ids and their bodies each in one buffer
    (item ``i``'s ends at ``id_ends[i]``, ``body_ends[i]``). What a decoding process sends
    back: a few buffers, not an object an item."""

    ids: bytes
    id_ends: np.ndarray  # int64
    boxes: np.ndarray  # (n, 4) float64
    bodies: bytes
    body_ends: np.ndarray  # int64

    @classmethod
    def concat(cls, parts: list[Columns]) -> Columns:
        if len(parts) == 1:
            return parts[0]
        return cls(
            b"".join(p.ids for p in parts),
            _ends([p.id_ends for p in parts]),
            np.concatenate([p.boxes for p in parts]) if parts else np.empty((0, 4)),
            b"".join(p.bodies for p in parts),
            _ends([p.body_ends for p in parts]),
        )

    def __len__(self) -> int:
        return len(self.boxes)

    def columns(self) -> Columns:
        return self

    def lines(self) -> bytes:
        """The items as NDJSON lines, each ending in a newline (JSON never holds a raw one)."""
        return np.insert(np.frombuffer(self.bodies, np.uint8), self.body_ends, 10).tobytes()


class _Box(Struct):
    """An item's box, the rest of its JSON passed over."""

    x0: float
    y0: float
    x1: float
    y1: float


_box_decoder = msgspec.json.Decoder(_Box)


def boxes_of(bodies: bytes, ends: np.ndarray) -> np.ndarray:
    """The (n, 4) float64 boxes of items' JSON packed one after another (item ``i``'s ends at
    ``ends[i]``), each exactly its item's: a body's floats are written to read back the same
    double (~0.45 s for 1M). What a store keeps instead of a second copy of every box.

    :raises ValueError: if a body is not an item's JSON
    """
    try:
        lines = np.insert(np.frombuffer(bodies, np.uint8), ends, 10).tobytes()
        found = _box_decoder.decode_lines(lines)
    except (*_UNREADABLE, msgspec.ValidationError) as error:
        raise ValueError(f"not items' JSON: {_why(error, lines)}") from None
    boxes = np.empty((len(found), 4), np.float64)
    for col, name in enumerate(_COORDS):
        boxes[:, col] = np.fromiter(map(attrgetter(name), found), np.float64, len(found))
    return boxes


T = TypeVar("T")
Make = Callable[[list["Item"], int, Callable[[int], str]], T]  # batch_of, columns_of
_decoder = msgspec.json.Decoder(Item)
_array_decoder = msgspec.json.Decoder(list[Item])
_encoder = msgspec.json.Encoder()
_COORDS = ("x0", "y0", "x1", "y1")


def decode_item(body: bytes, max_data_bytes: int, item_id: str) -> Batch:
    """The item of a single-item edit: ``body`` is its JSON; ``id`` may be left out.

    :raises ItemError: naming the field and why, or a body ``id`` other than ``item_id``
    """
    try:
        raw = msgspec.json.decode(body)
        if isinstance(raw, dict) and raw.setdefault("id", item_id) != item_id:
            raise ItemError(f"id {raw['id']!r} in the body does not match {item_id!r} in the URL")
        item = msgspec.convert(raw, Item)
    except (*_UNREADABLE, msgspec.ValidationError) as error:
        raise ItemError(_why(error, body)) from None
    return batch_of([item], max_data_bytes)


def decode_ndjson(
    body: Readable, max_line_bytes: int, max_data_bytes: int, block_bytes: int = BLOCK_BYTES
) -> Iterator[Batch]:
    """Batches of the items in an NDJSON stream, read a block of lines at a time.

    A block holding one item a line is decoded in one call. Any other's item lines (blank
    ones, white space only, are passed over and counted) are found by one regular expression
    in C, so a body of blank lines costs what its bytes do, not a Python step per line; line
    numbers are worked out only for an error's message.

    :raises ItemError: "line N: why" for the first bad line (a line too long first, in a
        block of ``block_bytes``); a line over ``max_line_bytes`` is refused once that many
        bytes of it are read, not after
    """
    for block in ndjson_blocks(body, max_line_bytes, block_bytes):
        yield from ndjson_block(*block, max_line_bytes, max_data_bytes, batch_of)


def ndjson_blocks(
    body: Readable, max_line_bytes: int, block_bytes: int = BLOCK_BYTES
) -> Iterator[tuple[bytes, int, int]]:
    """The stream cut into blocks of whole lines, ``(data, end, first)``: the lines are
    ``data[:end]``, the first of them line number ``first``. ``ndjson_block`` decodes one; a
    process may decode each (see ``importers.ndjson``).

    :raises ItemError: for a line over ``max_line_bytes``, once that many bytes of it are read
    """
    first, pending = 1, b""  # the line number at the start of the block; a line begun before it
    while True:
        read = body.read(block_bytes)
        data = pending + read if pending else read
        end = data.rfind(b"\n") + 1 if read else len(data)  # whole lines only, until the last
        yield data, end, first
        if not read:
            return
        first += data.count(b"\n", 0, end)
        pending = data[end:]
        if len(pending) > max_line_bytes:
            raise line_too_long(first, max_line_bytes)


def ndjson_block(
    data: bytes,
    end: int,
    first: int,
    max_line_bytes: int,
    max_data_bytes: int,
    make: Make[T],
    newlines: np.ndarray | None = None,
) -> Iterator[T]:
    """The batches of one block of ``ndjson_blocks``, made by ``make`` (``batch_of``, or
    ``columns_of``: packed); ``newlines``: ``newlines_in(data, end)``, if the caller has them.

    :raises ItemError: "line N: why" for its first bad line (a line too long first)
    """
    whole = _whole_block(data, end, max_line_bytes, newlines_in(data, end) if newlines is None else newlines)
    lines: list[bytes] = []
    if whole is None:  # a blank line, a long one or a bad one: line by line
        lines = _ITEM_LINE.findall(data, 0, end)
        if lines and max(map(len, lines)) > max_line_bytes:
            row = next(i for i, line in enumerate(lines) if len(line) > max_line_bytes)
            raise line_too_long(_line_number(data, first, row), max_line_bytes)
    for start in range(0, len(lines) if whole is None else len(whole), LINES_PER_BATCH):
        number = partial(_line_number, data, first, offset=start)
        items = (
            _decoded(lines[start : start + LINES_PER_BATCH], number)
            if whole is None
            else whole[start : start + LINES_PER_BATCH]
        )
        yield make(items, max_data_bytes, lambda row: f"line {number(row)}: ")


def newlines_in(data: bytes, end: int) -> np.ndarray:
    """Where the newlines of ``data[:end]`` are."""
    return np.flatnonzero(np.frombuffer(data, np.uint8, end) == 10)


def _whole_block(data: bytes, end: int, max_line_bytes: int, newlines: np.ndarray) -> list[Item] | None:
    """The items of ``data[:end]`` (its ``newlines``) decoded in one call, when it holds one a
    line: no blank line, none over ``max_line_bytes``, none bad or holding two values (msgspec
    passes over blank lines and reads the values a line holds one after another: the items
    then fall short of the lines or outnumber them). None otherwise, for ``_decoded`` to find
    which line, line by line. Not cutting the block into lines first saves ~15% of its decoding."""
    if _blank_line(data, end, newlines):
        return None
    lines = len(newlines) + (end > 0 and data[end - 1] != 10)  # the last may end the body, not a line
    if np.diff(newlines, prepend=-1, append=end).max(initial=0) - 1 > max_line_bytes:
        return None  # its blanks may make it short enough: ``_ITEM_LINE`` decides
    try:
        items = _decoder.decode_lines(memoryview(data)[:end])
    except _UNREADABLE:
        return None
    return items if len(items) == lines else None


def _blank_line(data: bytes, end: int, newlines: np.ndarray) -> bool:
    """Whether a line of ``data[:end]`` ended by a newline holds only whitespace. Only a line
    that begins with whitespace can (an empty one begins with its newline), so the search is
    made only when one does: a block of items begins each line with ``{`` (searching every
    block took ~1.1 s of a 10M board's decoding, across its processes)."""
    starts = np.empty(len(newlines), np.int64)
    starts[:1] = 0
    np.add(newlines[:-1], 1, out=starts[1:])
    if not _SPACE[np.frombuffer(data, np.uint8, end)[starts]].any():
        return False
    return bool(_BLANK_LINE.search(data, 0, end) or _BLANK_FIRST.match(data, 0, end))


def _decoded(lines: list[bytes], number: Callable[[int], int]) -> list[Item]:
    """The items of ``lines``, the item lines of a block; ``number(row)``: line ``row``'s number."""
    try:
        items = _decoder.decode_lines(b"\n".join(lines))
    except _UNREADABLE:
        items = []
    if len(items) != len(lines):  # a bad line, or one holding two values
        for row, line in enumerate(lines):
            try:
                _decoder.decode(line)
            except _UNREADABLE as error:
                raise ItemError(f"line {number(row)}: {_why(error, line)}") from None
    return items


def _line_number(data: bytes, first: int, row: int, offset: int = 0) -> int:
    """The number of item line ``offset + row`` of the block ``data`` whose first line is ``first``."""
    for k, line in enumerate(_ITEM_LINE.finditer(data)):
        if k == offset + row:
            return first + data.count(b"\n", 0, line.start())
    raise AssertionError("no such item line")


def line_too_long(number: int, max_line_bytes: int) -> ItemError:
    return ItemError(f"line {number}: longer than {max_line_bytes} bytes, the limit (VANTAGE_MAX_LINE_BYTES)")


def decode_json_array(body: Readable, max_data_bytes: int) -> Iterator[Batch]:
    """Batches of the items of a JSON array (a convenience beside NDJSON: it is read whole).

    :raises ItemError: "item N: why" for the first bad item, or why it is not an array of items
    """
    try:
        data = body.read()
        items = _array_decoder.decode(data)
    except _UNREADABLE as error:
        raise ItemError(f"the body is not a JSON array of items: {_why(error, data)}") from None
    except msgspec.ValidationError as error:
        raise ItemError(f"the JSON array: {error}") from None
    for start in range(0, len(items), LINES_PER_BATCH):
        yield batch_of(
            items[start : start + LINES_PER_BATCH], max_data_bytes, lambda row: f"item {start + row}: "
        )


def _why(error: Exception, data: bytes | memoryview) -> str:
    """Why ``data`` could not be decoded, as ``error`` (a decoder's) tells."""
    if isinstance(error, RecursionError):
        return f"nested too deeply (at most {MAX_DATA_DEPTH} levels in `data`)"
    bad = bad_utf8(data, error)
    return f"not valid UTF-8 ({bad})" if bad else str(error)


def bad_utf8(data: bytes | memoryview, error: Exception) -> str | None:
    """Where ``data`` stops being UTF-8, ``"byte 0xff at offset 12"``, if ``error`` is a
    decoder's refusal of it for that (else None). msgspec says the byte and its place
    within the string, or from 0.23 only "Invalid UTF-8 encoded string": found here."""
    if not isinstance(error, UnicodeDecodeError) and "UTF-8" not in str(error):
        return None
    try:
        bytes(data).decode()
    except UnicodeDecodeError as found:
        return f"byte {found.object[found.start]:#04x} at offset {found.start}"
    return None


def batch_of(items: list[Item], max_data_bytes: int, where: Callable[[int], str] = lambda row: "") -> Batch:
    """Items as columns, with the checks a type cannot state: finite, ordered boxes; small data.

    :raises ItemError: starting with ``where(row)`` of the first bad item
    """
    boxes, ids = _checked(items, max_data_bytes, where)
    return Batch(ids, boxes, list(map(_encoder.encode, items)))


def columns_of(
    items: list[Item], max_data_bytes: int, where: Callable[[int], str] = lambda row: ""
) -> Columns:
    """``batch_of``'s items packed: the same checks, the same bytes, no object an item.

    :raises ItemError: starting with ``where(row)`` of the first bad item
    """
    boxes, ids = _checked(items, max_data_bytes, where)
    return Columns(*_lines_packed(ids), boxes, *_lines_packed(items))


def _checked(
    items: list[Item], max_data_bytes: int, where: Callable[[int], str]
) -> tuple[np.ndarray, list[str]]:
    """The items' boxes and ids, once every item passed the checks a type cannot state.

    :raises ItemError: starting with ``where(row)`` of the first bad item
    """
    n = len(items)
    boxes = np.empty((n, 4), np.float64)
    for col, name in enumerate(_COORDS):
        boxes[:, col] = np.fromiter(map(attrgetter(name), items), np.float64, n)
    bad = first_bad_box(boxes)
    if bad is not None:
        row, why = bad
        raise ItemError(where(row) + why)
    ids = [item.id for item in items]
    joined = "\n".join(ids)  # one scan in C; item by item only when it finds something
    if "\x00" in joined or joined.startswith(AGG_PREFIX) or "\n" + AGG_PREFIX in joined:
        for row, item_id in enumerate(ids):
            if item_id.startswith(AGG_PREFIX):
                raise ItemError(
                    f"{where(row)}id {item_id!r} starts with '~', which marks aggregates; choose another"
                )
            if "\x00" in item_id:  # PostgreSQL's text cannot hold it: no store takes such an id
                raise ItemError(f"{where(row)}id {item_id!r} holds a NUL character (\\u0000); choose another")
    for row, item in enumerate(items):
        if item.data is not UNSET:
            data = _encoder.encode(item.data)
            if len(data) > max_data_bytes:
                raise ItemError(
                    f"{where(row)}data is {len(data)} bytes as JSON; the limit is {max_data_bytes} "
                    "(VANTAGE_MAX_DATA_BYTES)"
                )
            if data.count(b"[") + data.count(b"{") > MAX_DATA_DEPTH and _depth(item.data) > MAX_DATA_DEPTH:
                raise ItemError(
                    f"{where(row)}data is nested {_depth(item.data)} levels deep; the limit is "
                    f"{MAX_DATA_DEPTH}"
                )
    return boxes, ids


def _lines_packed(values: list[Any]) -> tuple[bytes, np.ndarray]:
    """Each value's JSON in one buffer, and where each ends: encoded as NDJSON in one call,
    then its newlines taken out (JSON never holds a raw one, so each ends a value)."""
    lines = _encoder.encode_lines(values)
    ends = np.flatnonzero(np.frombuffer(lines, np.uint8) == 10)
    ends -= np.arange(len(ends))
    return lines.replace(b"\n", b""), ends  # one pass in C: 2x sooner than numpy's delete


def _ends(parts: list[np.ndarray]) -> np.ndarray:
    """The ends of items packed one after another, from each part's own."""
    starts = np.cumsum([0] + [p[-1] if len(p) else 0 for p in parts[:-1]])
    return (
        np.concatenate([p + s for p, s in zip(parts, starts, strict=True)])
        if parts
        else np.empty(0, np.int64)
    )


def _depth(value: object) -> int:
    """Levels of nesting of a decoded JSON value (a scalar is 0)."""
    depth, level = 0, [value]
    while level:
        depth += 1
        level = [
            v
            for c in level
            if isinstance(c, (dict, list))
            for v in (c.values() if isinstance(c, dict) else c)
        ]
        level = [c for c in level if isinstance(c, (dict, list))]
    return depth
