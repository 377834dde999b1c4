"""A big NDJSON file is decoded by a process a core, a block of lines each: the items, and the
first bad line an error names, are exactly those of the decoder the server runs in-process."""

import contextlib
import io
import json
import tempfile
from collections.abc import Iterator
from itertools import pairwise
from pathlib import Path
from unittest.mock import patch

import numpy as np
import orjson
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app import items
from app.cli import main
from app.config import get_settings
from app.importers import base, ndjson
from app.importers.ndjson import decode_in_parallel
from app.items import Columns, ItemError, decode_ndjson
from app.registry import Registry
from app.snapfile import SnapshotFiles
from app.stores import SQLiteStore

MAX_LINE = 300  # bytes: the tests' lines are short, and a few are made longer than this

_ID = st.text(st.characters(codec="utf-8", exclude_characters="\x00"), min_size=1, max_size=12)
_ITEM = st.builds(
    lambda item_id, x, y, w, kind, data: json.dumps(
        {"id": item_id, "x0": x, "y0": y, "x1": x + w, "y1": y + w, "kind": kind}
        | ({"data": data} if data is not None else {}),
        ensure_ascii=False,
    ),
    _ID,
    st.floats(-1e6, 1e6),
    st.floats(-1e6, 1e6),
    st.floats(0, 100),
    st.sampled_from(["box", "text"]),
    st.none() | st.dictionaries(st.sampled_from("ab"), st.integers(), max_size=2),
)
_BAD = st.sampled_from(
    [
        "{not json",
        '{"id": "m", "x0": 0}',  # a field missing
        '{"id": "~a", "x0": 0, "y0": 0, "x1": 1, "y1": 1}',  # an aggregate's id
        '{"id": "inv", "x0": 5, "y0": 0, "x1": 1, "y1": 1}',  # inverted
        '{"id": "long", "x0": 0, "y0": 0, "x1": 1, "y1": 1, "data": {"t": "' + "x" * MAX_LINE + '"}}',
    ]
)
_LINE = _ITEM | st.sampled_from(["", "   "]) | _BAD


def _split(buffer: bytes, ends: np.ndarray) -> list[bytes]:
    starts = [0, *ends.tolist()]
    return [buffer[a:b] for a, b in pairwise(starts)]


def _outcome(decoded) -> list[tuple[str, list[float], bytes]] | str:
    """Every item the decoder's batches hold, in order, ``(JSON id, box, body)``; or the error
    it raised. Each batch read on its own terms: a list an item, or packed buffers."""
    out = []
    try:
        for batch in decoded:
            if isinstance(batch, Columns):
                ids, bodies = _split(batch.ids, batch.id_ends), _split(batch.bodies, batch.body_ends)
                ids = [orjson.loads(i) for i in ids]
            else:
                ids, bodies = batch.ids, batch.bodies
            out += zip(ids, batch.boxes.tolist(), bodies, strict=True)
    except ItemError as error:
        return str(error)
    return out


@contextlib.contextmanager
def _opened(body: bytes, as_file: bool) -> Iterator[io.BufferedIOBase]:
    """``body`` to read: a stream (a gzip file's, say), or a plain file, whose blocks the
    processes read where they lie."""
    if not as_file:
        yield io.BytesIO(body)
        return
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "items.ndjson"
        path.write_bytes(body)
        with path.open("rb") as file:
            yield file


@pytest.mark.parametrize("as_file", [False, True])
@pytest.mark.parametrize("block", [64, 200, 256])
def test_a_line_too_long_found_while_reading_waits_for_the_blocks_before_it(block, as_file):
    """The reader finds the long line blocks ahead of the processes: the bad line before it,
    in a block still being decoded, is the one named."""
    good = '{"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1}'
    body = "\n".join([good, good, "{not json", good, "y" * 5 * MAX_LINE, good]).encode()
    with _opened(body, as_file) as read:
        said = _outcome(decode_in_parallel(read, MAX_LINE, 4096, 2, block))
    assert said == _outcome(decode_ndjson(io.BytesIO(body), MAX_LINE, 4096, block))
    assert said.startswith("line 3: JSON is malformed")


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    lines=st.lists(_LINE, max_size=40),
    block=st.integers(1, 2000),
    newline=st.booleans(),
    as_file=st.booleans(),
)
def test_decoded_in_processes_as_in_one(lines, block, newline, as_file):
    """Blocks of a few bytes to a few hundred: lines are cut across them, a line too long is
    found while reading (or in a block), and errors in several blocks name the first; the
    same whether the processes are sent the blocks or read them from the file."""
    body = ("\n".join(lines) + ("\n" if newline else "")).encode()
    with patch.object(items, "LINES_PER_BATCH", 1):  # a block's batches, packed, joined in one
        alone = _outcome(decode_ndjson(io.BytesIO(body), MAX_LINE, 4096, block))
        with _opened(body, as_file) as read:
            assert _outcome(decode_in_parallel(read, MAX_LINE, 4096, 2, block)) == alone
            if as_file and not isinstance(alone, str):  # read through, as far as its reader can tell
                assert read.tell() == len(body)


_ODD = st.sampled_from(
    [
        '{"id": "t", "x0": 0, "y0": 0, "x1": 1, "y1": 1} {"id": "u", "x0": 0, "y0": 0, "x1": 1, "y1": 1}',
        '  {"id": "s", "x0": 0, "y0": 0, "x1": 1, "y1": 1}\t',  # blanks around an item
        '{"id": "r", "x0": 0, "y0": 0, "x1": 1, "y1": 1}\r',  # a line ended as CRLF
        "\t",
        "\r",
        "\x0c",  # blank to the line finder, not to JSON
        "\x0b \x0c",
    ]
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(lines=st.lists(_LINE | _ODD, max_size=30), block=st.integers(1, 3000), newline=st.booleans())
def test_a_block_decoded_in_one_call_reads_as_line_by_line(lines, block, newline):
    """A block with one item a line is decoded in one call, not cut into lines first; any
    other (a blank line, two values on one, a bad one, a long one) line by line, as before:
    the same items, or the same error naming the same line."""
    body = ("\n".join(lines) + ("\n" if newline else "")).encode()
    at_once = _outcome(decode_ndjson(io.BytesIO(body), MAX_LINE, 4096, block))
    with patch.object(items, "_whole_block", lambda *_: None):
        assert at_once == _outcome(decode_ndjson(io.BytesIO(body), MAX_LINE, 4096, block))


def test_a_block_of_one_item_a_line_is_decoded_in_one_call():
    """The fast path is taken where it can be (else the test above compares the slow path
    with itself), and left where a line is blank or holds two values."""
    good = '{"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1}'
    for body, whole in [
        (f"{good}\n{good}\n", True),
        (f"{good}\r\n {good}", True),
        (f"{good}\n\n{good}\n", False),
        (f"\n{good}\n", False),
        (f"{good}\n \t\n{good}\n", False),
        (f"{good} {good}\n{good}\n", False),
        (f"{good}\n{good}\n ", False),  # a last line of blanks: no item
        (f"{good}\n\r\n{good}\n", False),
        (f"\x0b\x0c\n{good}\n{good}\n", False),
    ]:
        data = body.encode()
        found = items._whole_block(data, len(data), MAX_LINE, items.newlines_in(data, len(data)))
        assert (found is not None) == whole, body
        if whole:
            assert [i.id for i in found] == ["a", "a"]


@given(st.lists(st.sampled_from([b"{}", b"a", b" ", b"\t", b"\r", b"\n", b"\x0b", b"\x0c"]), max_size=30))
def test_a_blank_line_is_found_where_the_search_finds_one(pieces):
    """A block's blank lines (whitespace, then a newline) are searched for only where a line
    begins with whitespace: found exactly where a search of every line finds them."""
    data = b"".join(pieces)
    for end in {len(data), data.rfind(b"\n") + 1}:
        searched = items._BLANK_LINE.search(data, 0, end) or items._BLANK_FIRST.match(data, 0, end)
        assert items._blank_line(data, end, items.newlines_in(data, end)) == bool(searched), data[:end]


def test_packed_items_go_on_as_the_same_ndjson_lines():
    """What ``vantage import --url`` streams of a big file: each item's line, as one process
    makes them."""
    rows = [{"id": f"é{n}", "x0": n, "y0": 0, "x1": n + 1, "y1": 1, "data": {"t": "a\nb"}} for n in range(50)]
    body = b"".join(orjson.dumps(row) + b"\n" for row in rows)
    alone = b"".join(batch.lines() for batch in decode_ndjson(io.BytesIO(body), MAX_LINE, 4096))
    packed = b"".join(c.lines() for c in decode_in_parallel(io.BytesIO(body), MAX_LINE, 4096, 2, 500))
    assert packed == alone and alone.count(b"\n") == 50


def _items(data_dir) -> dict[str, tuple[bytes, list[float]]]:
    store = SQLiteStore(data_dir)
    try:
        registry = Registry(store, SnapshotFiles(data_dir / "snapshots"), 1 << 30)
        [meta] = store.documents()
        table = registry[meta["id"]].snapshot.table
        boxes = table.read_boxes()
        return {table.item_id(i): (bytes(table.bodies[i]), boxes[i].tolist()) for i in range(len(table))}
    finally:
        store.close()


def test_a_big_file_is_imported_by_processes_as_by_one(tmp_path, monkeypatch, capsys):
    path = tmp_path / "big.ndjson"
    rows = [
        {"id": f"i{n % 900}", "x0": n, "y0": -n, "x1": n + 1.5, "y1": 2, "data": {"n": n}}
        for n in range(3000)
    ]
    path.write_bytes(b"".join(orjson.dumps(row) + b"\n" for row in rows))  # repeated ids: upserts
    get_settings.cache_clear()
    main(["import", str(path), "--data-dir", str(tmp_path / "one")])
    monkeypatch.setattr(ndjson, "PARALLEL_BYTES", 0)  # 32 MiB otherwise
    monkeypatch.setattr(base.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(items, "LINES_PER_BATCH", 7)  # a block's batches joined into one
    seen = []
    real = ndjson.decode_in_parallel
    monkeypatch.setattr(ndjson, "decode_in_parallel", lambda *a, **k: seen.append(a) or real(*a, 4096, **k))
    main(["import", str(path), "--data-dir", str(tmp_path / "two")])
    assert seen, "the parallel decoder ran"
    one, two = _items(tmp_path / "one"), _items(tmp_path / "two")
    assert len(two) == 900 and two == one
    assert orjson.loads(two["i5"][0])["data"] == {"n": 2705}  # the last of its id

    rows[2500]["x1"] = -1  # inverted: nothing of the file is stored
    path.write_bytes(b"".join(orjson.dumps(row) + b"\n" for row in rows))
    capsys.readouterr()
    try:
        main(["import", str(path), "--doc", "big", "--data-dir", str(tmp_path / "two")])
    except SystemExit as stop:
        assert stop.code == 1
    assert "line 2501:" in capsys.readouterr().err
    assert _items(tmp_path / "two") == one
    assert np.array_equal(sorted(one), sorted(f"i{n}" for n in range(900)))


def test_a_line_with_no_end_is_refused_once_past_the_limit_not_read_whole(tmp_path):
    """A file's cuts are found by the reading process: a line over the limit (a file of one
    huge line, say) stops the cutting there, and no process is given it whole."""
    good = b'{"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1}\n'
    path = tmp_path / "one-line.ndjson"
    path.write_bytes(good + b"y" * 50 * MAX_LINE)
    with path.open("rb") as file:
        cut = ndjson._file_blocks(file, MAX_LINE, 64)
        assert next(cut) == (file.fileno(), 0, len(good))
        with pytest.raises(ndjson._TooLong):
            next(cut)
        said = _outcome(decode_in_parallel(file, MAX_LINE, 4096, 2, 64))
    assert said == f"line 2: longer than {MAX_LINE} bytes, the limit (VANTAGE_MAX_LINE_BYTES)"
