"""NDJSON, one item a line, as the server's import takes it; gzipped too (found by its magic
bytes, whatever the name). Decoded by the server's own decoder: the same checks, the same
"line N" in an error. A big file is decoded by a process a core, a block of lines each, in
order: the items come back packed (``Columns``), and the first bad line is still the one named.
"""

from __future__ import annotations

import gzip
import multiprocessing
import signal
import zlib
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path

import msgspec

from ..items import (
    BLOCK_BYTES,
    Batch,
    Columns,
    Readable,
    columns_of,
    decode_ndjson,
    ndjson_block,
    ndjson_blocks,
)
from .base import ImportFailed, Source, processes

NAME = "NDJSON"
SUFFIXES = (".ndjson", ".jsonl", ".ndjson.gz")
GZIP = b"\x1f\x8b"
PARALLEL_BYTES = 32 << 20  # from this size, decoded by a process a core (a pool costs ~0.1 s to start)


def detect(path: Path, head: bytes) -> bool:
    if head.startswith(GZIP) or path.suffix.lower() in (".ndjson", ".jsonl"):
        return True
    first = next((line for line in head.splitlines() if line.strip()), b"")
    try:
        value = msgspec.json.decode(first)
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError):  # not an item: another format's
        return False
    return isinstance(value, dict) and "x0" in value


def batches(source: Source, max_line_bytes: int, max_data_bytes: int) -> Iterator[Batch | Columns]:
    """:raises ItemError: "line N: why"; ImportFailed: a damaged gzip file"""
    workers = processes()
    parallel = source.size >= PARALLEL_BYTES and workers > 1
    with source.path.open("rb") as raw:
        zipped = raw.read(2) == GZIP
        raw.seek(0)
        body = gzip.GzipFile(fileobj=raw, mode="rb") if zipped else raw
        try:
            decoded = (
                decode_in_parallel(body, max_line_bytes, max_data_bytes, workers)
                if parallel
                else decode_ndjson(body, max_line_bytes, max_data_bytes)
            )
            for batch in decoded:
                source.done = raw.tell()
                yield batch
        except (OSError, EOFError, zlib.error) as error:
            if not zipped:
                raise
            raise ImportFailed(
                f"not a whole gzip file ({error}): decompress it (gunzip -t names the damage) or "
                "export it again"
            ) from None


def decode_in_parallel(
    body: Readable, max_line_bytes: int, max_data_bytes: int, workers: int, block_bytes: int = BLOCK_BYTES
) -> Iterator[Columns]:
    """``decode_ndjson``'s items, a block of ``block_bytes`` at a time decoded by one of
    ``workers`` processes (forked: nothing to import again), in order. Two blocks a worker are
    in flight at most, so memory holds a few blocks whatever the file's size.

    :raises ItemError: as ``decode_ndjson`` does, for the same first bad line: a block read
        after a bad one is never decoded, and an error found while reading (a line too long,
        a damaged gzip stream) waits for the blocks before it
    """
    pool = ProcessPoolExecutor(workers, multiprocessing.get_context("fork"), _leave_interrupts)
    window: deque[Future[Columns]] = deque()
    blocks: Iterator[tuple[bytes, int, int]] | None = ndjson_blocks(body, max_line_bytes, block_bytes)
    failed: BaseException | None = None
    try:
        while True:
            while failed is None and blocks is not None and len(window) < 2 * workers:
                try:
                    block = next(blocks)
                except StopIteration:
                    blocks = None
                except Exception as error:  # raised once the blocks before it are decoded
                    failed = error
                else:
                    window.append(pool.submit(_columns, *block, max_line_bytes, max_data_bytes))
            if not window:
                break
            yield window.popleft().result()
        if failed is not None:
            raise failed
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _leave_interrupts() -> None:
    """In a worker: Ctrl-C is the command's to handle (it stops the pool), not each worker's
    to print a traceback for."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _columns(data: bytes, end: int, first: int, max_line_bytes: int, max_data_bytes: int) -> Columns:
    """One block's items, in a worker process."""
    return Columns.concat(list(ndjson_block(data, end, first, max_line_bytes, max_data_bytes, columns_of)))
