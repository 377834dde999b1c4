"""CSV (or TSV) with a header: columns id, x0, y0, x1, y1 required, kind and z optional, any
others go into the item's ``data`` as strings (an empty cell is left out)."""

from __future__ import annotations

import csv
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .base import ImportFailed, Source

__all__ = ["NAME", "OPTIONAL", "REQUIRED", "SUFFIXES", "detect", "read"]

NAME = "CSV"
SUFFIXES = (".csv", ".tsv")
REQUIRED = ("id", "x0", "y0", "x1", "y1")
OPTIONAL = ("kind", "z")


def detect(path: Path, head: bytes) -> bool:
    if path.suffix.lower() in SUFFIXES:
        return True
    first = head.removeprefix(b"\xef\xbb\xbf").split(b"\n", 1)[0].decode("utf-8", "replace")
    names = {name.strip() for name in first.replace("\t", ",").split(",")}
    return set(REQUIRED) <= names


def read(source: Source) -> Iterator[tuple[str, dict]]:
    with source.path.open("rb") as file:
        rows = csv.reader(_lines(file, source), delimiter=_delimiter(source.path, file))
        header = [name.strip() for name in next(rows, [])]
        missing = [name for name in REQUIRED if name not in header]
        if missing:
            raise ImportFailed(
                f"row 1 (the header) has no column {', '.join(map(repr, missing))}: the first row "
                f"names the columns, and {', '.join(REQUIRED)} are required ({', '.join(OPTIONAL)} "
                "optional; others go into data)"
            )
        repeated = sorted({name for name in header if header.count(name) > 1})
        if repeated:
            raise ImportFailed(f"row 1 (the header) names {', '.join(map(repr, repeated))} twice: rename one")
        at = {name: header.index(name) for name in (*REQUIRED, *OPTIONAL) if name in header}
        extra = [(i, name) for i, name in enumerate(header) if name not in at and name]
        for number, row in enumerate(_checked(rows), 2):  # as a spreadsheet numbers them: the header is 1
            if not any(cell.strip() for cell in row):
                continue
            if len(row) != len(header):
                raise ImportFailed(
                    f"row {number}: {len(row)} cells where the header has {len(header)}: "
                    "quote a cell holding the delimiter"
                )
            item: dict[str, Any] = {"id": row[at["id"]]}
            for name in ("x0", "y0", "x1", "y1"):
                item[name] = _number(row[at[name]], float, number, name)
            if "kind" in at and row[at["kind"]].strip():
                item["kind"] = row[at["kind"]].strip()
            if "z" in at and row[at["z"]].strip():
                item["z"] = _number(row[at["z"]], int, number, "z")
            data = {name: row[i] for i, name in extra if row[i] != ""}
            if data:
                item["data"] = data
            yield f"row {number}", item


def _checked(rows: Any) -> Iterator[list[str]]:
    """The reader's rows; what it cannot read (a cell over its field limit) named by row."""
    number = 1
    while True:
        number += 1
        try:
            row = next(rows)
        except StopIteration:
            return
        except csv.Error as error:
            raise ImportFailed(
                f"row {number}: {error}: a cell holds at most 128 kB (and data 4 kB)"
            ) from None
        yield row


def _lines(file: Any, source: Source) -> Iterator[str]:
    """The file's lines, decoded, counting the bytes read for the progress bar."""
    for number, line in enumerate(file, 1):
        source.done += len(line)
        try:
            yield line.decode("utf-8-sig" if number == 1 else "utf-8")
        except UnicodeDecodeError as error:
            raise ImportFailed(
                f"line {number} is not UTF-8 (byte {line[error.start]:#04x} at column {error.start + 1}): "
                "save the file as UTF-8"
            ) from None


def _delimiter(path: Path, file: Any) -> str:
    first = file.readline()
    file.seek(0)
    return "\t" if path.suffix.lower() == ".tsv" or (b"\t" in first and b"," not in first) else ","


def _number(cell: str, kind: type, row: int, column: str) -> Any:
    try:
        return kind(cell)
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise ImportFailed(f"row {row}, column {column!r}: {cell!r} is not {what}") from None
