"""`vantage import`: each format read from a real file the test writes, against the boxes it
drew; the command into a local store (read back through the store and a registry) and through
a real server (read back with GET /viewport); errors name the file and the record, and store
nothing."""

import ctypes
import gzip
import json
import math
from pathlib import Path

import httpx
import orjson
import pytest

from app.cli import main
from app.client import Client
from app.config import get_settings
from app.importers import FORMATS, ImportFailed, Source, batches, detect
from app.launch import launch
from app.registry import Registry
from app.snapfile import SnapshotFiles
from app.stores import SQLiteStore

BIG = {"x0": -1e9, "y0": -1e9, "x1": 1e9, "y1": 1e9, "limit": 100_000}


def _items(path: Path, columns: int = 1) -> dict[str, dict]:
    """What the importers make of ``path``: ``{id: item}``."""
    module = detect(path)
    found = {}
    for batch in batches(Source.of(path, columns=columns), module, 1 << 16, 4096):
        for body in batch.bodies:
            item = orjson.loads(body)
            found[item["id"]] = item
    return found


def _box(item: dict) -> tuple:
    return tuple(round(item[k], 6) for k in ("x0", "y0", "x1", "y1"))


def _import(*args: str) -> None:
    """``vantage import`` in this process; fails the test if it exits non-zero."""
    get_settings.cache_clear()
    try:
        main(["import", *args])
    except SystemExit as stop:
        raise AssertionError(f"vantage import exited {stop.code}") from None


def _refused(capsys, *args: str) -> str:
    """What ``vantage import`` says as it exits non-zero."""
    get_settings.cache_clear()
    with pytest.raises(SystemExit) as stop:
        main(["import", *args])
    assert stop.value.code == 1
    return capsys.readouterr().err


def _stored(data_dir: Path) -> dict[str, dict[str, dict]]:
    """The store's documents by name, each ``{item id: item}``, as a registry opens them."""
    store = SQLiteStore(data_dir)
    try:
        registry = Registry(store, SnapshotFiles(data_dir / "snapshots"), 1 << 30)
        out = {}
        for meta in store.documents():
            table = registry[meta["id"]].snapshot.stored_table() or store.read_items(meta["id"])
            items = [orjson.loads(table.bodies[i]) for i in range(len(table))]
            out[meta["name"]] = {item["id"]: item for item in items}
        return out
    finally:
        store.close()


# -- files the tests write -----------------------------------------------------------------------

ITEMS = [
    {"id": "a", "x0": 0.0, "y0": 0.0, "x1": 10.0, "y1": 20.0, "kind": "box", "z": 1},
    {"id": "b", "x0": -5.5, "y0": 3.0, "x1": 7.25, "y1": 4.0, "kind": "text", "z": 0, "data": {"text": "hi"}},
    {"id": "c", "x0": 100.0, "y0": 200.0, "x1": 300.0, "y1": 400.0, "kind": "image", "z": -3},
]


def _ndjson(path: Path, items=ITEMS, zipped: bool = False) -> Path:
    body = b"".join(orjson.dumps(item) + b"\n" for item in items)
    path.write_bytes(gzip.compress(body) if zipped else body)
    return path


def _pdf(path: Path, pages: int = 2) -> Path:
    """A PDF drawn with PDFium: each US-letter page with the words "Hello" at (72, 700) and
    "brave new world" at (300, 500), 12 pt Helvetica (PDF space: y up from the bottom), a
    filled rectangle (100, 100)-(300, 150) and a 100x50 image at (200, 300)."""
    import pypdfium2 as pdfium
    import pypdfium2.raw as c

    pdf = pdfium.PdfDocument.new()
    font = c.FPDFText_LoadStandardFont(pdf, b"Helvetica")
    for _ in range(pages):
        page = pdf.new_page(612, 792)
        for text, x, y in (("Hello", 72, 700), ("brave new world", 300, 500)):
            obj = c.FPDFPageObj_CreateTextObj(pdf, font, ctypes.c_float(12))
            wide = (text + "\0").encode("utf-16-le")
            c.FPDFText_SetText(obj, ctypes.cast(ctypes.c_char_p(wide), c.FPDF_WIDESTRING))
            c.FPDFPageObj_Transform(obj, 1, 0, 0, 1, x, y)
            c.FPDFPage_InsertObject(page, obj)
        rect = c.FPDFPageObj_CreateNewRect(100, 100, 200, 50)
        c.FPDFPageObj_SetFillColor(rect, 200, 30, 30, 255)
        c.FPDFPath_SetDrawMode(rect, c.FPDF_FILLMODE_ALTERNATE, 0)
        c.FPDFPage_InsertObject(page, rect)
        image = pdfium.PdfImage.new(pdf)
        bitmap = pdfium.PdfBitmap.new_native(4, 2, c.FPDFBitmap_BGR)
        bitmap.fill_rect((0, 128, 255, 255), 0, 0, 4, 2)
        image.set_bitmap(bitmap)
        image.set_matrix(pdfium.PdfMatrix().scale(100, 50).translate(200, 300))
        page.insert_obj(image)
        page.gen_content()
    pdf.save(str(path))
    return path


# -- the formats ---------------------------------------------------------------------------------


def test_the_registry_lists_every_format_once():
    assert [f.NAME for f in FORMATS] == ["NDJSON", "PDF", "Excalidraw", "tldraw", "JSON array", "CSV"]


def test_ndjson_plain_and_gzipped_by_its_magic_bytes_whatever_the_name(tmp_path):
    plain = _ndjson(tmp_path / "items.ndjson")
    zipped = _ndjson(tmp_path / "items.data", zipped=True)  # no .gz: found by its first bytes
    for path in (plain, zipped):
        assert _items(path) == {item["id"]: item for item in ITEMS}


def test_a_json_array_of_items(tmp_path):
    path = tmp_path / "items.json"
    path.write_text(json.dumps(ITEMS, indent=2))
    assert _items(path) == {item["id"]: item for item in ITEMS}


def test_csv_required_columns_optional_ones_and_the_rest_as_data(tmp_path):
    path = tmp_path / "boxes.csv"
    path.write_text(
        'id,x0,y0,x1,y1,kind,z,label,page\na,0,0,10,20,box,1,first,\nb,-5.5,3,7.25,4,,,"with, comma",2\n'
    )
    assert _items(path) == {
        "a": {"id": "a", "x0": 0.0, "y0": 0.0, "x1": 10.0, "y1": 20.0, "kind": "box", "z": 1, "data": {"label": "first"}},
        "b": {
            "id": "b", "x0": -5.5, "y0": 3.0, "x1": 7.25, "y1": 4.0, "kind": "box", "z": 0,
            "data": {"label": "with, comma", "page": "2"},
        },
    }  # fmt: skip


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ("id,x0,y0,x1\na,0,0,1\n", "row 1 (the header) has no column 'y1'"),
        ("id,x0,y0,x1,y1\na,0,0,1,1\nb,0,zero,1,1\n", "row 3, column 'y0': 'zero' is not a number"),
        ("id,x0,y0,x1,y1,z\na,0,0,1,1,1.5\n", "row 2, column 'z': '1.5' is not an integer"),
        ("id,x0,y0,x1,y1\na,0,0,1,1\nb,5,0,1,1\n", "row 3: x0=5.0 > x1=1.0; swap them"),
        ("id,x0,y0,x1,y1\na,0,0,1\n", "row 2: 4 cells where the header has 5"),
    ],
)
def test_csv_errors_name_the_row_and_the_column(tmp_path, text, said):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ImportFailed) as error:
        _items(path)
    assert str(error.value).startswith(f"{path}: ") and said in str(error.value)


def test_pdf_pages_words_images_and_drawings_where_they_were_drawn(tmp_path):
    items = _items(_pdf(tmp_path / "report.pdf"))
    pages = {i: item for i, item in items.items() if item["kind"] == "page"}
    assert {i: _box(p) for i, p in pages.items()} == {"p1": (0, 0, 612, 792), "p2": (0, 816, 612, 1608)}
    for number, top in ((1, 0.0), (2, 816.0)):
        mine = {i: item for i, item in items.items() if i.startswith(f"p{number}") and i != f"p{number}"}
        words = sorted((item for item in mine.values() if item["kind"] == "text"), key=lambda w: w["x0"])
        assert [w["data"]["text"] for w in words] == ["Hello", "brave", "new", "world"]
        hello, brave, new, world = words
        # Baselines at y = 792 - 700 and 792 - 500 on the canvas: the font's line, from its
        # ascent above (about an em at 12 pt) to its descent below
        for word, x, baseline in ((hello, 72, 92), (brave, 300, 292)):
            assert x <= word["x0"] < x + 2 and top + baseline - 12.5 < word["y0"] < top + baseline - 8.5
            assert top + baseline + 1 < word["y1"] < top + baseline + 4
        assert brave["x1"] < new["x0"] < new["x1"] < world["x0"]
        # the words of a line are as tall as one another, "new" (no ascender) as "brave"
        assert {(w["y0"], w["y1"]) for w in (brave, new, world)} == {(brave["y0"], brave["y1"])}
        assert 300 + 2 * 30 < world["x1"] < 300 + 12 * 15 * 0.6  # 15 characters of ~0.5 em
        [drawing] = [item for item in mine.values() if item["kind"] == "drawing"]
        assert _box(drawing) == (100, top + 642, 300, top + 692)
        [image] = [item for item in mine.values() if item["kind"] == "image"]
        assert _box(image) == (200, top + 442, 300, top + 492)
        assert (pages[f"p{number}"]["z"], drawing["z"], image["z"], hello["z"]) == (0, 1, 2, 3)


def test_pdf_pages_in_columns(tmp_path):
    items = _items(_pdf(tmp_path / "report.pdf", pages=3), columns=2)
    pages = {i: _box(item) for i, item in items.items() if item["kind"] == "page"}
    assert pages == {"p1": (0, 0, 612, 792), "p2": (636, 0, 1248, 792), "p3": (0, 816, 612, 1608)}
    assert _box(items["p2i0"]) == (836, 442, 936, 492)


def test_excalidraw_bounds_of_turned_elements_and_points_deleted_left_out(tmp_path):
    scene = {
        "type": "excalidraw",
        "version": 2,
        "source": "https://excalidraw.com",
        "elements": [
            {"id": "r", "type": "rectangle", "x": 10, "y": 20, "width": 100, "height": 50, "angle": math.pi / 2},
            {"id": "gone", "type": "ellipse", "x": 0, "y": 0, "width": 5, "height": 5, "angle": 0, "isDeleted": True},
            {"id": "l", "type": "arrow", "x": 100, "y": 100, "width": 30, "height": 40, "angle": 0,
             "points": [[0, 0], [30, -40], [-10, 5]]},
            {"id": "t", "type": "text", "x": 0, "y": 0, "width": 40, "height": 20, "angle": math.pi / 4,
             "text": "note"},
        ],
        "appState": {},
        "files": {},
    }  # fmt: skip
    path = tmp_path / "board.excalidraw"
    path.write_text(json.dumps(scene, indent=2))
    items = _items(path)
    assert set(items) == {"r", "l", "t"}
    assert _box(items["r"]) == (35, -5, 85, 95)  # 100 x 50 turned a quarter about (60, 45)
    assert _box(items["l"]) == (90, 60, 130, 105)
    half = round(30 * math.sqrt(2) / 2, 6)  # a 40 x 20 box turned 45 degrees about (20, 10)
    assert _box(items["t"]) == (
        round(20 - half, 6),
        round(10 - half, 6),
        round(20 + half, 6),
        round(10 + half, 6),
    )
    assert (items["r"]["kind"], items["l"]["kind"], items["t"]["data"]) == (
        "rectangle",
        "arrow",
        {"text": "note"},
    )
    assert items["r"]["z"] < items["l"]["z"] < items["t"]["z"]


def test_tldraw_page_bounds_through_frames_and_groups(tmp_path):
    def shape(id, type, x, y, parent="page:one", rotation=0.0, index="a1", **props):
        return {"typeName": "shape", "id": f"shape:{id}", "type": type, "x": x, "y": y,
                "rotation": rotation, "parentId": parent, "index": index, "props": props}  # fmt: skip

    records = [
        {"typeName": "document", "id": "document:document", "name": ""},
        {"typeName": "page", "id": "page:one", "name": "One", "index": "a1"},
        {"typeName": "page", "id": "page:two", "name": "Two", "index": "a2"},
        shape("frame", "frame", 100, 100, w=400, h=300, name="F"),
        shape("inframe", "geo", 10, 20, parent="shape:frame", w=50, h=60, geo="rectangle", text="hi"),
        shape("turned", "frame", 0, 0, rotation=math.pi / 2, index="a2", w=100, h=100),
        shape("inturned", "geo", 10, 0, parent="shape:turned", w=20, h=10),
        shape("group", "group", 500, 500, index="a3"),
        shape("g1", "geo", 0, 0, parent="shape:group", w=10, h=10),
        shape("g2", "geo", 20, 20, parent="shape:group", index="a2", w=10, h=10),
        shape("line", "line", 50, 50, index="a4", points={"a": {"id": "a", "index": "a1", "x": 0, "y": 0},
                                                           "b": {"id": "b", "index": "a2", "x": -20, "y": 30}}),
        shape("other", "geo", 0, 0, parent="page:two", w=10, h=10),
    ]  # fmt: skip
    path = tmp_path / "board.tldr"
    path.write_text(json.dumps({"tldrawFileFormatVersion": 1, "schema": {}, "records": records}))
    items = _items(path)
    boxes = {i.removeprefix("shape:"): _box(item) for i, item in items.items()}
    assert boxes == {
        "frame": (100, 100, 500, 400),
        "inframe": (110, 120, 160, 180),
        "turned": (-100, 0, 0, 100),
        "inturned": (-10, 10, 0, 30),
        "group": (500, 500, 530, 530),
        "g1": (500, 500, 510, 510),
        "g2": (520, 520, 530, 530),
        "line": (30, 50, 50, 80),
        "other": (730, 0, 740, 10),  # page two, to the right of page one's shapes (up to 530)
    }
    z = {i.removeprefix("shape:"): item["z"] for i, item in items.items()}
    assert (
        z["frame"] < z["inframe"] < z["turned"] < z["inturned"] < z["group"] < z["g1"] < z["g2"] < z["line"]
    )
    assert items["shape:inframe"]["kind"] == "geo" and items["shape:inframe"]["data"]["text"] == "hi"


def _deep_rich_text(levels: int) -> bytes:
    """A tldraw document whose one note's richText nests ``levels`` paragraphs deep (written as
    text: a JSON encoder would refuse the depth)."""
    node = (
        b'{"type": "paragraph", "content": [' * levels + b'{"type": "text", "text": "deep"}' + b"]}" * levels
    )
    note = {"typeName": "shape", "id": "shape:n", "type": "note", "parentId": "page:p", "index": "a1"}
    note |= {"x": 0, "y": 0, "rotation": 0, "props": {"richText": {"type": "doc", "content": ["NODE"]}}}
    page = {"typeName": "page", "id": "page:p", "index": "a1", "name": "Page"}
    document = {"tldrawFileFormatVersion": 1, "schema": {}, "records": [page, note]}
    return json.dumps(document).encode().replace(b'"NODE"', node)


NESTED = b"[" * 1000 + b"]" * 1000


@pytest.mark.parametrize(
    ("name", "content", "said"),
    [
        ("bad.json", b'[{"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1, "kind": "\xff"}]', "not UTF-8"),
        (
            "deep.json",
            b'[{"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1, "data": ' + NESTED + b"}]",
            "nested too deeply",
        ),
        (
            "bad.excalidraw",
            b'{"type": "excalidraw", "elements": [{"id": "\xff"}]}',
            "the byte 0xff at offset 44",
        ),
        ("deep.excalidraw", b'{"type": "excalidraw", "elements": ' + NESTED + b"}", "nested too deeply"),
        ("bad.tldr", b'{"tldrawFileFormatVersion": 1, "records": [{"id": "\xff"}]}', "not UTF-8"),
        ("deep.tldr", _deep_rich_text(2000), "nested too deeply"),
        (
            "bad.ndjson",
            b'{"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1, "kind": "\xff"}\n',
            "line 1: not valid UTF-8",
        ),
        ("wide.csv", b"id,x0,y0,x1,y1,note\na,0,0,1,1," + b"x" * 140_000 + b"\n", "row 2: field larger than"),
    ],
)
def test_an_unreadable_file_is_one_line_of_error_never_a_traceback(tmp_path, capsys, name, content, said):
    path = tmp_path / name
    path.write_bytes(content)
    error = _refused(capsys, str(path), "--data-dir", str(tmp_path / "data")).strip()
    assert error.splitlines()[-1].startswith(f"vantage import: {path}: ") and said in error, error
    assert "Traceback" not in error


def test_rich_text_nested_deep_but_readable_is_read_whole(tmp_path):
    path = tmp_path / "deep.tldr"
    path.write_bytes(_deep_rich_text(450))  # within the JSON reader's depth, past Python's recursion
    (note,) = _items(path).values()
    assert note["data"]["text"] == "deep"


def test_csv_errors_name_the_row_a_spreadsheet_shows_when_a_cell_spans_lines(tmp_path):
    path = tmp_path / "quoted.csv"
    path.write_text('id,x0,y0,x1,y1,note\na,0,0,1,1,"two\nlines"\nb,0,0,x,1,one\n')
    with pytest.raises(ImportFailed, match="row 3, column 'x1'"):  # the file's line 4
        _items(path)


def test_a_file_in_no_known_format_is_named_with_the_fix(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("just some words\n")
    with pytest.raises(ImportFailed, match=r"notes.txt: not a format vantage import reads.*NDJSON"):
        detect(path)


EXCALIDRAW = {
    "type": "excalidraw",
    "elements": [{"id": "r", "type": "rectangle", "x": 1, "y": 2, "width": 3, "height": 4}],
}


@pytest.mark.parametrize(
    ("name", "write"),
    [
        ("report.pdf", lambda path: _pdf(path, pages=1)),
        ("items.ndjson", _ndjson),
        ("items.json", lambda path: path.write_text(json.dumps(ITEMS))),
        ("boxes.csv", lambda path: path.write_text("id,x0,y0,x1,y1,label\na,0,0,10,20,first\n")),
        ("board.excalidraw", lambda path: path.write_text(json.dumps(EXCALIDRAW))),
    ],
)
def test_every_format_gzipped_is_read_by_its_content_whatever_the_name(tmp_path, name, write):
    plain = tmp_path / name
    write(plain)
    for zipped in (tmp_path / f"{name}.gz", tmp_path / "download"):  # named, or not at all
        zipped.write_bytes(gzip.compress(plain.read_bytes()))
        assert detect(zipped) is detect(plain)
        assert _items(zipped) == _items(plain), zipped
    assert not list(tmp_path.glob(".gunzipped-*")), "the decompressed copy is removed once read"


@pytest.mark.parametrize(
    ("content", "said"),
    [
        (b"", "an empty file; there is nothing in it to import"),
        (
            b"PK\x03\x04\x14\x00[Content_Types].xml xl/workbook.xml",
            "an Excel workbook (.xlsx); save its sheet as CSV",
        ),
        (b"\x89PNG\r\n\x1a\n\x00\x00", "a PNG image; put it in a PDF"),
        (
            b"<!DOCTYPE html><html><body>Not found</body></html>",
            "an HTML page; a download may have saved the page",
        ),
        (b"BZh91AY&SY", "compressed with bzip2; decompress it (bunzip2)"),
        ("id;x;y\n".encode("utf-16"), "text in UTF-16; save it as UTF-8"),
        (b"just some words\n", "plain text, not CSV with a header id,x0,y0,x1,y1; convert it to NDJSON"),
        (
            gzip.compress(b"%!PS-Adobe-3.0\n", mtime=0),
            "a gzip file holding PostScript; convert it to PDF (ps2pdf",
        ),
    ],
)
def test_a_file_in_no_known_format_says_what_it_looks_like_and_what_to_do(tmp_path, capsys, content, said):
    path = tmp_path / "upload"
    path.write_bytes(content)
    error = _refused(capsys, str(path), "--data-dir", str(tmp_path / "data")).strip()
    assert error.startswith(f"vantage import: {path}: not a format vantage import reads: {said}"), error
    assert "gzipped too" in error and "Traceback" not in error


def test_a_gzip_file_cut_short_says_so_before_or_after_its_format_is_known(tmp_path, capsys):
    whole = gzip.compress(_pdf(tmp_path / "report.pdf", pages=3).read_bytes())
    early, late = tmp_path / "early.pdf.gz", tmp_path / "late.pdf.gz"
    early.write_bytes(whole[:20])  # not even the format's first bytes
    late.write_bytes(whole[: len(whole) // 2])  # a PDF, its end missing
    for path in (early, late):
        error = _refused(capsys, str(path), "--data-dir", str(tmp_path / "data"))
        assert f"{path}: not a whole gzip file" in error and "gunzip -t" in error, error
    assert not list(tmp_path.glob("**/.gunzipped-*"))


# -- the command ---------------------------------------------------------------------------------


def test_import_into_the_local_store_upserts_or_replaces(tmp_path, capsys):
    data = tmp_path / "data"
    first = _ndjson(tmp_path / "first.ndjson")
    _import(str(first), "--data-dir", str(data))
    assert "3 items into 'first'" in capsys.readouterr().out
    assert _stored(data) == {"first": {item["id"]: item for item in ITEMS}}
    assert list((data / "snapshots").glob("*.vsnap")), (
        "the snapshot file is written, as the server's import does"
    )

    second = tmp_path / "second.csv"
    second.write_text("id,x0,y0,x1,y1\nc,1,2,3,4\nd,5,6,7,8\n")
    _import(str(second), "--doc", "first", "--data-dir", str(data))  # by name: an upsert
    assert set(_stored(data)["first"]) == {"a", "b", "c", "d"}
    assert _box(_stored(data)["first"]["c"]) == (1, 2, 3, 4)

    [meta] = SQLiteStore(data).documents()
    _import(str(second), "--doc", meta["id"], "--replace", "--data-dir", str(data))  # by id
    assert set(_stored(data)["first"]) == {"c", "d"}
    assert len(list((data / "snapshots").glob("*.vsnap"))) == 1


def test_import_a_gzipped_pdf_into_the_local_store_as_debian_ships_them(tmp_path, capsys):
    data = tmp_path / "data"
    zipped = tmp_path / "manual.pdf.gz"
    zipped.write_bytes(gzip.compress(_pdf(tmp_path / "plain.pdf", pages=2).read_bytes()))
    _import(str(zipped), "--data-dir", str(data))
    assert "14 items into 'manual'" in capsys.readouterr().out  # named without .pdf.gz
    items = _stored(data)["manual"]
    assert items["p1w0"]["data"] == {"text": "Hello"} and _box(items["p2"]) == (0, 816, 612, 1608)
    assert not list(data.rglob(".gunzipped-*")), "the decompressed copy is removed once read"


def test_import_pdf_into_the_local_store_in_columns(tmp_path):
    data = tmp_path / "data"
    _import(str(_pdf(tmp_path / "report.pdf", pages=2)), "--columns", "2", "--data-dir", str(data))
    items = _stored(data)["report"]
    assert _box(items["p2"]) == (636, 0, 1248, 792) and items["p1w0"]["data"] == {"text": "Hello"}


def test_a_bad_record_stores_nothing_and_is_named(tmp_path, capsys):
    data = tmp_path / "data"
    bad = tmp_path / "bad.csv"
    bad.write_text("id,x0,y0,x1,y1\n" + "".join(f"i{n},0,0,1,1\n" for n in range(40_000)) + "late,0,0,x,1\n")
    said = _refused(capsys, str(bad), "--data-dir", str(data))
    assert f"{bad}: row 40002, column 'x1': 'x' is not a number" in said
    unknown = tmp_path / "picture.bmp"
    unknown.write_bytes(b"BM\x00\x01")
    assert f"{unknown}: not a format vantage import reads" in _refused(
        capsys, str(unknown), "--data-dir", str(data)
    )
    assert _stored(data) == {}


def test_import_through_a_server_streams_and_reads_back_the_same(tmp_path, capsys):
    data = tmp_path / "data"
    server, url = launch(data)
    try:
        pdf = _pdf(tmp_path / "report.pdf", pages=3)
        _import(str(pdf), "--url", url, "--doc", "Report")
        assert "into 'Report'" in capsys.readouterr().out
        with Client(url) as client:
            [doc] = client.documents()
            shown = client.viewport(doc["id"], (-1e9, -1e9, 1e9, 1e9), limit=100_000)["items"]
            assert {item["id"]: item for item in shown} == _items(pdf)

            # A bad record late in the file aborts the upload: nothing stored, the document
            # the command made for it deleted again.
            bad = tmp_path / "late.ndjson"
            _ndjson(bad, [*ITEMS, *({"id": f"i{n}", "x0": 0, "y0": 0, "x1": 1, "y1": 1} for n in range(30_000)),
                          {"id": "z", "x0": 0}])  # fmt: skip
            said = _refused(capsys, str(bad), "--url", url)
            assert f"{bad}: line 30004: Object missing required field `y0`" in said
            assert [d["name"] for d in client.documents()] == ["Report"]
            assert client.describe(doc["id"])["items"] == len(shown)

            small = _ndjson(tmp_path / "small.ndjson", ITEMS[:1])
            assert client.supports_replace()  # the route's mode=replace, found in its OpenAPI schema
            _import(str(small), "--url", url, "--doc", doc["id"], "--replace")
            assert [i["id"] for i in client.viewport(doc["id"], (-1e9, -1e9, 1e9, 1e9))["items"]] == ["a"]
    finally:
        server.terminate()
        server.communicate(timeout=10)


def test_a_server_refusal_is_named(tmp_path, capsys):
    data = tmp_path / "data"
    server, url = launch(data, env={"VANTAGE_TOKENS": "secret"})
    try:
        said = _refused(capsys, str(_ndjson(tmp_path / "x.ndjson")), "--url", url)
        assert f"the server at {url} refused: 401" in said and "--token" in said
        _import(str(tmp_path / "x.ndjson"), "--url", url, "--token", "secret")
        assert (
            httpx.get(f"{url}/documents", headers={"authorization": "Bearer secret"}).json()[0]["items"] == 3
        )
    finally:
        server.terminate()
        server.communicate(timeout=10)


def test_pdf_pages_read_by_worker_processes_are_the_same(tmp_path, monkeypatch):
    from app.importers import base, pdf

    path = _pdf(tmp_path / "report.pdf", pages=5)
    alone = _items(path, columns=2)
    monkeypatch.setattr(pdf, "PARALLEL_PAGES", 2)  # a process a core from 2 pages (64 otherwise)
    monkeypatch.setattr(base.os, "cpu_count", lambda: 2)
    assert _items(path, columns=2) == alone and len(alone) == 5 * 7  # a page, 4 words, a drawing, an image


def test_csv_header_names_are_read_as_people_write_them_and_each_only_once(tmp_path):
    spaced = tmp_path / "spaced.csv"
    spaced.write_text("id, x0, y0 ,x1,y1 , kind\na,0,0,1,1,note\n")  # spaces around the names
    assert _items(spaced)["a"]["kind"] == "note"
    repeated = tmp_path / "repeated.csv"
    repeated.write_text("id,x0,y0,x1,y1,label,label\na,0,0,1,1,first,second\n")
    with pytest.raises(ImportFailed, match="names 'label' twice"):
        _items(repeated)
