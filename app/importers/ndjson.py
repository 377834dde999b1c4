"""NDJSON, one item a line, as the server's import takes it; gzipped too (found by its magic
bytes, whatever the name), read as a stream. Decoded by the server's own decoder: the same checks, the same
"line N" in an error. A big file is decoded by a process a core, a block of lines each, in
order: the items come back packed (``Columns``), and the first bad line is still the one named.
"""

from __future__ import annotations

import contextlib
import gzip
import io
import multiprocessing
import os
import signal
import stat
import tempfile
import zlib
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np

from ..items import (
    BLOCK_BYTES,
    Batch,
    Columns,
    ItemError,
    Readable,
    columns_of,
    decode_ndjson,
    line_too_long,
    ndjson_block,
    ndjson_blocks,
    newlines_in,
)
from .base import ImportFailed, Source, processes

__all__ = ["NAME", "SUFFIXES", "batches", "decode_in_parallel", "detect"]

NAME = "NDJSON"
SUFFIXES = (".ndjson", ".jsonl")
GZIP = b"\x1f\x8b"
PARALLEL_BYTES = 32 << 20  # from this size, decoded by a process a core (a pool costs ~0.1 s to start)


def detect(path: Path, head: bytes) -> bool:
    """Whether ``head`` (a gzip file's: what it holds, ``path`` its name without ``.gz``) is
    NDJSON items, or the name says so."""
    if path.suffix.lower() in (".ndjson", ".jsonl"):
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
                decode_in_parallel(body, max_line_bytes, max_data_bytes, workers, scratch=source.scratch)
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
    body: Readable,
    max_line_bytes: int,
    max_data_bytes: int,
    workers: int,
    block_bytes: int = BLOCK_BYTES,
    *,
    scratch: Path | None = None,
) -> Iterator[Columns]:
    """``decode_ndjson``'s items, a block of ``block_bytes`` at a time decoded by one of
    ``workers`` processes (forked: nothing to import again), in order. Two blocks a worker are
    in flight at most, so memory holds a few blocks whatever the file's size.

    Nothing big goes through a pipe (pickled, sent, received and unpickled, that was most of
    what the reading process did: a third of a core): a plain file's blocks are read by the
    processes where they lie (the cuts found here by reading a little before each, the file
    moved past each block as it is decoded, as if read), and each process writes a block's
    columns to the file of its slot (with no name, in ``scratch``, made before the processes
    fork so that each has them), read back here. A stream's (a gzip file's) blocks are cut
    here and sent.

    :raises ItemError: as ``decode_ndjson`` does, for the same first bad line: a block read
        after a bad one is never decoded, and an error found while reading (a line too long,
        a damaged gzip stream) waits for the blocks before it
    """
    window: deque[tuple[Future[_Written], int, _Block]] = deque()
    plain = _plain_file(body)
    blocks: Iterator[_Block] | None = (
        _file_blocks(plain, max_line_bytes, block_bytes)
        if plain is not None
        else ((data, end) for data, end, _ in ndjson_blocks(body, max_line_bytes, block_bytes))
    )
    failed: BaseException | None = None
    lines = 0  # the lines of the blocks before the next: a process numbers its block's from 1
    if scratch is not None:
        scratch.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as files:
        slots = [
            files.enter_context(tempfile.TemporaryFile(dir=scratch)).fileno() for _ in range(2 * workers)
        ]
        free = deque(slots)
        pool = ProcessPoolExecutor(workers, multiprocessing.get_context("fork"), _leave_interrupts)
        try:
            while True:
                while failed is None and blocks is not None and free:
                    try:
                        block = next(blocks)
                    except StopIteration:
                        blocks = None
                    except Exception as error:  # raised once the blocks before it are decoded
                        failed = error
                    else:
                        slot = free.popleft()
                        decoding = pool.submit(_decoded_into, block, slot, max_line_bytes, max_data_bytes)
                        window.append((decoding, slot, block))
                if not window:
                    break
                future, slot, block = window.popleft()
                try:
                    written = future.result()
                except ItemError:
                    raise _numbered(block, lines + 1, max_line_bytes, max_data_bytes) from None
                columns = written.read(slot)
                free.append(slot)
                lines += written.lines
                if plain is not None:  # read, as far as the caller can tell (its progress)
                    plain.seek(written.stop)
                yield columns
            if isinstance(failed, _TooLong):
                raise line_too_long(lines + 1, max_line_bytes)
            if failed is not None:
                raise failed
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


# A block's lines: sent, ``(data, end)``, or where they lie, ``(fd, start, stop)``
_Block = tuple[bytes, int] | tuple[int, int, int]


class _TooLong(Exception):
    """A line over the limit, found while cutting a file: it begins after the blocks cut so far."""


def _plain_file(body: Readable) -> io.BufferedReader | None:
    """``body`` if it is a regular file (not a stream of one): its blocks can be read where
    they lie."""
    if not isinstance(body, io.BufferedReader):
        return None
    return body if stat.S_ISREG(os.fstat(body.fileno()).st_mode) else None


def _file_blocks(
    file: io.BufferedReader, max_line_bytes: int, block_bytes: int
) -> Iterator[tuple[int, int, int]]:
    """``(fd, start, stop)`` of each block of whole lines of ``file`` from where it is, cut
    where ``ndjson_blocks`` cuts the same bytes read as a stream: at the last newline before
    each ``block_bytes`` more (so the blocks, and any error, are a stream's).

    :raises _TooLong: where ``ndjson_blocks`` finds a line too long (past a cut, unended)
    """
    fd = file.fileno()
    size, start = os.fstat(fd).st_size, file.tell()
    cut = start
    while cut < size:
        cut = min(cut + block_bytes, size)
        stop = _after_last_newline(fd, start, cut)
        if stop > start:
            yield fd, start, stop
        start = stop
        if cut - start > max_line_bytes:
            raise _TooLong
    if start < size:
        yield fd, start, size


def _after_last_newline(fd: int, start: int, stop: int, step: int = 1 << 16) -> int:
    """Just past the last newline of the file's bytes ``start:stop``; ``start`` if none."""
    while stop > start:
        at = max(start, stop - step)
        found = os.pread(fd, stop - at, at).rfind(b"\n")
        if found >= 0:
            return at + found + 1
        stop = at
    return start


def _numbered(block: _Block, first: int, max_line_bytes: int, max_data_bytes: int) -> ItemError:
    """The error a worker met in ``block`` as the one-process decoder names it: the block
    decoded again here, its first line numbered ``first`` (a worker numbers from 1, not
    knowing the lines before it)."""
    try:
        _columns(*_lines(block)[:2], first, max_line_bytes, max_data_bytes)
    except ItemError as numbered:
        return numbered
    raise AssertionError("a block a worker refused decodes here")


def _leave_interrupts() -> None:
    """In a worker: Ctrl-C is the command's to handle (it stops the pool), not each worker's
    to print a traceback for."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@dataclass(frozen=True)
class _Written:
    """A block's columns, written by a worker to its slot's file: how to read them back."""

    items: int
    id_bytes: int
    body_bytes: int
    lines: int  # the block's newlines
    stop: int  # where the block ends in its file (0: sent)

    def read(self, fd: int) -> Columns:
        n, at = self.items, self.id_bytes + self.body_bytes
        boxes, id_ends, body_ends = np.empty((n, 4)), np.empty(n, np.int64), np.empty(n, np.int64)
        for array in (boxes, id_ends, body_ends):
            _read_into(fd, array, at)
            at += array.nbytes
        ids, bodies = _read(fd, self.id_bytes, 0), _read(fd, self.body_bytes, self.id_bytes)
        return Columns(ids, id_ends, boxes, bodies, body_ends)


def _lines(block: _Block) -> tuple[bytes, int, int]:
    """A block's bytes, where its lines end in them, and where it ends in its file (0: sent)."""
    if len(block) == 3:
        source, start, stop = block
        data = _read(source, stop - start, start)
        return data, len(data), stop
    data, end = block
    return data, end, 0


def _columns(
    data: bytes,
    end: int,
    first: int,
    max_line_bytes: int,
    max_data_bytes: int,
    newlines: np.ndarray | None = None,
) -> Columns:
    """The items of a block's lines ``data[:end]``, the first numbered ``first``."""
    return Columns.concat(
        list(ndjson_block(data, end, first, max_line_bytes, max_data_bytes, columns_of, newlines))
    )


def _decoded_into(block: _Block, fd: int, max_line_bytes: int, max_data_bytes: int) -> _Written:
    """One block's items, in a worker process, written to the file ``fd`` (its slot's)."""
    data, end, stop = _lines(block)
    newlines = newlines_in(data, end)  # found once: the decoding's, and the lines the command counts
    columns = _columns(data, end, 1, max_line_bytes, max_data_bytes, newlines)
    at = 0
    arrays = (  # as ``_Written.read`` reads them back
        np.ascontiguousarray(columns.boxes, np.float64),
        np.ascontiguousarray(columns.id_ends, np.int64),
        np.ascontiguousarray(columns.body_ends, np.int64),
    )
    for part in (columns.ids, columns.bodies, *arrays):
        view = memoryview(part) if isinstance(part, bytes) else part.reshape(-1).view(np.uint8).data
        while view:
            done = os.pwrite(fd, view, at)
            view, at = view[done:], at + done
    return _Written(len(columns), len(columns.ids), len(columns.bodies), len(newlines), stop)


def _read(fd: int, size: int, at: int) -> bytes:
    """``size`` bytes of the file ``fd`` at ``at`` (a read may return fewer)."""
    parts = []
    while size:
        part = os.pread(fd, size, at)
        if not part:
            raise EOFError(f"the file ended {size} bytes short")
        parts.append(part)
        size, at = size - len(part), at + len(part)
    return parts[0] if len(parts) == 1 else b"".join(parts)


def _read_into(fd: int, array: np.ndarray, at: int) -> None:
    """``array``'s bytes read from the file ``fd`` at ``at``, in place."""
    view = array.reshape(-1).view(np.uint8).data
    while view:
        done = os.preadv(fd, [view], at)
        if not done:
            raise EOFError("a worker's file ended short")
        view, at = view[done:], at + done
