"""Edit files: what a document's edits since its base made of its snapshot, saved beside the
base's file (``<doc>.<base id>.vedits``), so that an open maps the base and takes the edits as
they were made, not one at a time again: ~0.3 ms an edit, which at 1e8 items, where edits
pile up to ~390k before a compaction, would be minutes.

It is a cache, as the snapshot file is: the store's edits are the truth. An open takes the
edits made up to the file's version from it, and those since from the store. A file that is
stale (of another base, newer than the store), unreadable or corrupt (an xxh3 sum covers
it) is passed over, and the edits are all replayed from the store.

A file is a header (``MAGIC``, the format, the version it holds, the payload's length and
sum), then the payload: the snapshot's edit layer, as msgpack, zstd-compressed.
"""

from __future__ import annotations

import logging
import os
import struct
from dataclasses import replace
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import xxhash
import zstandard
from immutables import Map

from .looks import Looks
from .snapshots import EditLog, Snapshot

__all__ = ["FORMAT", "load", "save", "saved_version"]

log = logging.getLogger("vantage.snapshots")
MAGIC = b"VEDITS\x00\x00"
FORMAT = 1
_HEADER = struct.Struct("<8sIQQQ")  # magic, format, version, payload bytes, payload sum
_ARRAY = 1  # msgpack extension code of a numpy array


def save(path: Path, snap: Snapshot) -> None:
    """Write ``snap``'s edits since its base to ``path``, whole or not at all (a file of its
    own, then renamed over): a reader sees the file before or after, never a part.

    :raises OSError: if it could not be written
    """
    assert snap.overview is not None and snap.looks is not None  # a base's, with its edits
    state = {
        "base_id": snap.base_id,
        "version": snap.version,
        "log_base": snap.base,
        "next_position": snap.next_position,
        "edits": snap.edits,
        "looks": list(snap.looks.names),
        "overlay": {
            "at": np.fromiter(snap.overlay.keys(), np.int64, len(snap.overlay)),
            "ids": [bytes(edit[0]) for edit in snap.overlay.values()],
            "bodies": [bytes(edit[1]) for edit in snap.overlay.values()],
        },
        "added": {"ids": list(snap.added.keys()), "at": np.fromiter(snap.added.values(), np.int64)},
        "removed": np.fromiter(snap.removed.keys(), np.int64, len(snap.removed)),
        "log": _log(snap),
        "tree": snap.tree.edits(),
        "overview": snap.overview.edits(),
    }
    payload = zstandard.ZstdCompressor(level=1).compress(msgspec.msgpack.encode(state, enc_hook=_encoded))
    header = _HEADER.pack(MAGIC, FORMAT, snap.version, len(payload), xxhash.xxh3_64_intdigest(payload))
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(temporary, "wb") as out:
            out.write(header)
            out.write(payload)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def saved_version(path: Path) -> int | None:
    """The version the file at ``path`` holds, from its header; None if there is none."""
    try:
        with open(path, "rb") as file:
            return _header(file.read(_HEADER.size))[0]
    except (OSError, ValueError):
        return None


def load(path: Path, base: Snapshot, newest: int) -> Snapshot | None:
    """``base`` (a base as mapped, no edits) with the edits of the file at ``path`` made again,
    if it holds edits of that base up to a version no newer than ``newest`` (the store's);
    else None (logged, when the file is there but unfit)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as error:
        log.warning("%s passed over: %s", path, error)
        return None
    try:
        snap = _loaded(data, base, newest)
    except (ValueError, KeyError, TypeError, msgspec.DecodeError, zstandard.ZstdError) as error:
        log.warning("%s passed over (its edits are replayed from the store): %s", path, error)
        return None
    return snap


def _loaded(data: bytes, base: Snapshot, newest: int) -> Snapshot | None:
    """The snapshot of ``load``, or None if the file is stale.

    :raises ValueError: (and the decoders' errors) if it is corrupt or not an edit file
    """
    version, size, digest = _header(data)
    payload = memoryview(data)[_HEADER.size :]
    if len(payload) != size or xxhash.xxh3_64_intdigest(payload) != digest:
        raise ValueError("its sum does not match: corrupt")
    if version > newest or version < base.version:
        return None  # of a version the store does not hold (a store restored from a backup), or older
    state = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(payload), ext_hook=_decoded)
    if state["base_id"] != base.base_id or state["version"] != version:
        return None  # of another base
    assert base.overview is not None  # a base is built with its overview
    overlay = state["overlay"]
    names = tuple(state["looks"])
    return replace(
        base,
        version=version,
        tree=base.tree.with_edits(state["tree"]),
        overlay=Map(
            zip(overlay["at"].tolist(), zip(overlay["ids"], overlay["bodies"], strict=True), strict=True)
        ),
        added=Map(zip(state["added"]["ids"], state["added"]["at"].tolist(), strict=True)),
        removed=Map((pos, None) for pos in state["removed"].tolist()),
        log=EditLog(state["log"]["versions"].tolist(), state["log"]["ids"]),
        base=state["log_base"],
        next_position=state["next_position"],
        overview=base.overview.with_edits(state["overview"]),
        looks=Looks(names, {name: code for code, name in enumerate(names)}),
        edits=state["edits"],
    )


def _header(data: bytes) -> tuple[int, int, int]:
    """``(version, payload bytes, payload sum)`` from the header at the start of ``data``.

    :raises ValueError: if it is not an edit file's header, of this format
    """
    if len(data) < _HEADER.size:
        raise ValueError("too short for a header")
    magic, form, version, size, digest = _HEADER.unpack_from(data)
    if magic != MAGIC or form != FORMAT:
        raise ValueError(f"not an edit file of format {FORMAT}")
    return version, size, digest


def _log(snap: Snapshot) -> dict[str, Any]:
    """The log's entries up to ``snap``'s version: the list is shared with later snapshots."""
    end = snap.log.upto(snap.version)
    return {"versions": np.array(snap.log.versions[:end], np.int64), "ids": snap.log.ids[:end]}


def _encoded(value: Any) -> msgspec.msgpack.Ext:
    if not isinstance(value, np.ndarray):
        raise NotImplementedError(f"{type(value).__name__} is not saved in an edit file")
    kind = value.dtype.str.encode()
    head = struct.pack(f"<B{len(kind)}sB{value.ndim}q", len(kind), kind, value.ndim, *value.shape)
    return msgspec.msgpack.Ext(_ARRAY, head + np.ascontiguousarray(value).tobytes())


def _decoded(code: int, data: memoryview) -> np.ndarray:
    if code != _ARRAY:
        raise ValueError(f"an extension {code} in an edit file")
    length = data[0]
    kind = bytes(data[1 : 1 + length]).decode()
    ndim = data[1 + length]
    at = 2 + length
    shape = struct.unpack_from(f"<{ndim}q", data, at)
    return np.frombuffer(data, np.dtype(kind), offset=at + 8 * ndim).reshape(shape).copy()
