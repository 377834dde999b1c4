"""A JSON array of items (a convenience: what a script dumps); read whole, so keep NDJSON for
large files."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from .base import ImportFailed, Source, json_of

__all__ = ["NAME", "SUFFIXES", "detect", "read"]

NAME = "JSON array"
SUFFIXES = (".json",)


def detect(path: Path, head: bytes) -> bool:
    return head.lstrip(b"\xef\xbb\xbf \t\r\n").startswith(b"[")


def read(source: Source) -> Iterator[tuple[str, dict]]:
    items = json_of(source, "fix it, or write NDJSON, one item a line")
    if not isinstance(items, list):
        raise ImportFailed("not a JSON array of items: write [{...}, {...}] or NDJSON, one item a line")
    n = max(len(items), 1)
    for i, item in enumerate(items):
        if not i % 4096:
            source.done = source.size * i // n
        if not isinstance(item, dict):
            raise ImportFailed(
                f"element {i} of the array: an item is an object with id, x0, y0, x1, y1, not "
                f"{type(item).__name__}"
            )
        yield f"element {i} of the array", item
    source.done = source.size
