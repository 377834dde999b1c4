"""NDJSON, one item a line, as the server's import takes it; gzipped too (found by its magic
bytes, whatever the name). Decoded by the server's own decoder: the same checks, the same
"line N" in an error."""

from __future__ import annotations

import gzip
import zlib
from collections.abc import Iterator
from pathlib import Path

import msgspec

from ..items import Batch, decode_ndjson
from .base import ImportFailed, Source

NAME = "NDJSON"
SUFFIXES = (".ndjson", ".jsonl", ".ndjson.gz")
GZIP = b"\x1f\x8b"


def detect(path: Path, head: bytes) -> bool:
    if head.startswith(GZIP) or path.suffix.lower() in (".ndjson", ".jsonl"):
        return True
    first = next((line for line in head.splitlines() if line.strip()), b"")
    try:
        value = msgspec.json.decode(first)
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError):  # not an item: another format's
        return False
    return isinstance(value, dict) and "x0" in value


def batches(source: Source, max_line_bytes: int, max_data_bytes: int) -> Iterator[Batch]:
    """:raises ItemError: "line N: why"; ImportFailed: a damaged gzip file"""
    with source.path.open("rb") as raw:
        zipped = raw.read(2) == GZIP
        raw.seek(0)
        body = gzip.GzipFile(fileobj=raw, mode="rb") if zipped else raw
        try:
            for batch in decode_ndjson(body, max_line_bytes, max_data_bytes):
                source.done = raw.tell()
                yield batch
        except (OSError, EOFError, zlib.error) as error:
            if not zipped:
                raise
            raise ImportFailed(
                f"not a whole gzip file ({error}): decompress it (gunzip -t names the damage) or "
                "export it again"
            ) from None
