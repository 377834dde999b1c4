"""Snapshot files: a document's built index and packed items in one file, mapped, not rebuilt.

Layout (little-endian)::

    magic "VANTSNAP"  u32 format  u32 directory length  u64 xxh3-64 of everything after the header
    directory: JSON {"meta": {...}, "arrays": {name: [dtype, shape, offset]}}
    the arrays, each starting on a 64-byte boundary (a node record stays one cache line)

A file is written to a temporary name, flushed to disk and renamed, so a reader sees a whole
file or none. ``read`` maps it read-only and checks its header, format and checksum before
anything is used: every worker process that maps the same file shares its pages through the
page cache, so N workers hold about one copy.
"""

from __future__ import annotations

import json
import mmap
import os
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xxhash

__all__ = ["FORMAT", "SnapshotFileError", "SnapshotFileMissing", "read", "write"]

FORMAT = 2  # 2: the text index for search
_MAGIC = b"VANTSNAP"
_HEADER = struct.Struct("<8sIIQ")  # magic, format, directory length, checksum
_ALIGN = 64


class SnapshotFileError(Exception):
    """A snapshot file that cannot be used: missing, unreadable, of another format, or corrupt."""


class SnapshotFileMissing(SnapshotFileError):
    """No snapshot file there: never written here (a replica's first open), or removed."""


def write(path: Path, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> int:
    """Write ``arrays`` and ``meta`` (JSON-able) to ``path`` atomically; the file's size.
    Streamed: no second copy of the arrays is made."""
    directory: dict[str, list] = {}
    offset = 0
    for name, array in arrays.items():
        offset = _aligned(offset)
        directory[name] = [array.dtype.str, list(array.shape), offset]
        offset += array.nbytes
    head = json.dumps({"meta": dict(meta), "arrays": directory}).encode()
    start = _aligned(_HEADER.size + len(head))  # where the arrays begin
    hasher = xxhash.xxh3_64()
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(temporary, "wb") as out:

            def put(data: bytes | memoryview) -> None:
                hasher.update(data)
                out.write(data)

            out.write(bytes(_HEADER.size))  # the header, once the checksum is known
            put(head + bytes(start - _HEADER.size - len(head)))
            at = 0
            for name, array in arrays.items():
                put(bytes(directory[name][2] - at))
                put(memoryview(np.ascontiguousarray(array).reshape(-1).view(np.uint8)))
                at = directory[name][2] + array.nbytes
            out.seek(0)
            out.write(_HEADER.pack(_MAGIC, FORMAT, len(head), hasher.intdigest()))
            out.flush()
            os.fsync(out.fileno())
    except BaseException:  # a full disk, say: nothing half-written stays behind
        temporary.unlink(missing_ok=True)
        raise
    os.replace(temporary, path)
    return start + offset


def _aligned(offset: int) -> int:
    return -(-offset // _ALIGN) * _ALIGN


def read(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray], int]:
    """``(meta, arrays, size)`` of the file at ``path``: read-only arrays over a shared map.

    :raises SnapshotFileError: if the file is missing, short, of another format or corrupt
    """
    try:
        with open(path, "rb") as source:
            mapped = mmap.mmap(source.fileno(), 0, access=mmap.ACCESS_READ)
    except FileNotFoundError:
        raise SnapshotFileMissing(f"{path}: no such file") from None
    except (OSError, ValueError) as error:  # ValueError: an empty file cannot be mapped
        raise SnapshotFileError(f"{path}: {error}") from None
    if len(mapped) < _HEADER.size:
        raise SnapshotFileError(f"{path}: {len(mapped)} bytes, shorter than a header")
    magic, version, head_size, checksum = _HEADER.unpack_from(mapped)
    if magic != _MAGIC or version != FORMAT:
        raise SnapshotFileError(f"{path}: not a snapshot file of format {FORMAT}")
    raw = np.frombuffer(mapped, np.uint8)
    if xxhash.xxh3_64_intdigest(memoryview(raw[_HEADER.size :])) != checksum:
        raise SnapshotFileError(f"{path}: checksum mismatch (the file is corrupt)")
    try:
        head = json.loads(bytes(raw[_HEADER.size : _HEADER.size + head_size]))
        start = _aligned(_HEADER.size + head_size)
        arrays = {}
        for name, (dtype, shape, offset) in head["arrays"].items():
            count = int(np.prod(shape)) if shape else 1
            arrays[name] = np.frombuffer(mapped, np.dtype(dtype), count, start + offset).reshape(shape)
    except (ValueError, KeyError, TypeError) as error:  # a checksum collision, in effect
        raise SnapshotFileError(f"{path}: unreadable directory ({error})") from None
    return head["meta"], arrays, len(mapped)
