"""Edit files: what a document's edits since its base made of its snapshot, saved beside the
base's file (``<doc>.<base id>.vedits``), so that an open maps the base and takes the edits as
they were made, not one at a time again: ~0.3 ms an edit, which at 1e8 items, where edits
pile up to ~390k before a compaction, would be minutes.

It is a cache, as the snapshot file is: the store's edits are the truth. An open takes the
edits made up to the file's version from it, and those since from the store. A version number
alone does not say which edits made it: a store restored from a backup, or one that lost its
last commits (``synchronous = NORMAL``, then a power cut), reaches the file's version again
with other edits. So a file records what it follows: the store's newest edits it holds
(``FOLLOWS`` of them, each item's id, version and a digest of its box and body), and an open
takes it only if the store still holds those (or newer edits of the same items, replayed
after it) and no other edit up to its version since the oldest of them. A file that is stale
(of another base, newer than the store, following other edits), unreadable or corrupt (an
xxh3 sum covers it) is passed over and removed, logged, and the edits are all replayed from
the store: a file left there would stand for the edits it holds once the store came back to
its version.

A file is a header (``MAGIC``, the format, the version it holds, the payload's length and
sum), then the payload: the snapshot's edit layer and what it follows, as msgpack,
zstd-compressed.
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol

import msgspec
import numpy as np
import xxhash
import zstandard
from immutables import Map

from .looks import Looks
from .snapshots import EditLog, Snapshot
from .table import Edit

__all__ = ["FOLLOWS", "FORMAT", "Stored", "load", "save", "saved_version"]

log = logging.getLogger("vantage.snapshots")
MAGIC = b"VEDITS\x00\x00"
FORMAT = 2  # 2: what the file follows (1's files are passed over: they record none)
FOLLOWS = 16  # the store's newest edits a file records, and an open checks against the store
_HEADER = struct.Struct("<8sIQQQ")  # magic, format, version, payload bytes, payload sum
_ARRAY = 1  # msgpack extension code of a numpy array


class Stored(Protocol):
    """What an edit file is checked against: a ``Store``'s reads of a document and its edits."""

    def document(self, doc_id: str) -> dict[str, Any]: ...

    def edits(self, doc_id: str, after: int = 0) -> list[Edit]: ...

    def last_edits(self, doc_id: str, upto: int, count: int) -> list[Edit]: ...


def save(path: Path, snap: Snapshot, store: Stored, doc_id: str) -> bool:
    """Write ``snap``'s edits since its base to ``path``, whole or not at all (a file of its
    own, then renamed over): a reader sees the file before or after, never a part. With them,
    what they follow: the store's newest edits up to ``snap``'s version (of document
    ``doc_id``), which ``snap`` was made of. False (nothing written) if no edit of the store's
    up to it stands (all edited again since): the file could not be checked at an open.

    :raises OSError: if it could not be written (nothing of it is left)
    :raises StoreUnavailable: if the store could not be read
    """
    assert snap.overview is not None and snap.looks is not None  # a base's, with its edits
    follows = [
        (item_id, version, _digest(box, body))
        for item_id, version, box, body in store.last_edits(doc_id, snap.version, FOLLOWS)
    ]
    if not follows:
        return False
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
        "follows": follows,
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
    return True


def saved_version(path: Path) -> int | None:
    """The version the file at ``path`` holds, from its header; None if there is none."""
    try:
        with open(path, "rb") as file:
            return _header(file.read(_HEADER.size))[0]
    except (OSError, ValueError):
        return None


def load(path: Path, base: Snapshot, newest: int, store: Stored, doc_id: str) -> Snapshot | None:
    """``base`` (a base as mapped, no edits) with the edits of the file at ``path`` made again,
    if it holds edits of that base up to a version no newer than ``newest`` (the store's,
    asked again if older: another worker may have written and saved since) and follows the
    store's edits of document ``doc_id``; else None. A file there but unfit is removed, with
    a warning saying why.

    :raises StoreUnavailable: if the store could not be read
    """
    try:
        with open(path, "rb") as file:
            data, inode = file.read(), os.fstat(file.fileno()).st_ino
    except FileNotFoundError:
        return None
    except OSError as error:
        log.warning("%s passed over: %s", path, error)
        return None
    try:
        snap = _loaded(data, base, newest, store, doc_id)
    except (ValueError, KeyError, TypeError, msgspec.DecodeError, zstandard.ZstdError) as error:
        why = str(error)
    else:
        if isinstance(snap, Snapshot):
            return snap
        why = snap
    log.warning("%s passed over and removed (its edits are replayed from the store): %s", path, why)
    with contextlib.suppress(OSError):  # unless another worker saved a file of its own there since
        if os.stat(path).st_ino == inode:
            path.unlink()
    return None


def _loaded(data: bytes, base: Snapshot, newest: int, store: Stored, doc_id: str) -> Snapshot | str:
    """The snapshot of ``load``, or why the file is stale.

    :raises ValueError: (and the decoders' errors) if it is corrupt or not an edit file
    """
    version, size, digest = _header(data)
    payload = memoryview(data)[_HEADER.size :]
    if len(payload) != size or xxhash.xxh3_64_intdigest(payload) != digest:
        raise ValueError("its sum does not match: corrupt")
    if version < base.version:
        return f"of version {version}, older than its base's {base.version}"
    if version > newest:
        newest = store.document(doc_id)["version"]
    if version > newest:  # the store lost the edits it holds: restored from a backup, or cut short
        return (
            f"of version {version}, newer than the store's {newest}: the store lost edits"
            " (restored from a backup, or its last commits cut short)"
        )
    state = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(payload), ext_hook=_decoded)
    if state["base_id"] != base.base_id or state["version"] != version:
        return f"of another base ({state['base_id']})"
    unfollowed = _unfollowed(state["follows"], version, store, doc_id)
    if unfollowed is not None:
        return unfollowed
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


def _unfollowed(follows: Sequence[Sequence[Any]], version: int, store: Stored, doc_id: str) -> str | None:
    """Why a file of ``version`` that records ``follows`` (``save``) does not follow the
    store's edits now; None if it does: each edit it follows still stored as it was, or
    edited again after ``version`` (replayed over it), at least one of them the former, and no
    other edit stored after the oldest of them up to ``version``. Cost: one read of the
    store's edits after that oldest (those after ``version`` the open replays anyway)."""
    if not follows:
        return "it follows none of the store's edits"
    named = {item_id: (at, digest) for item_id, at, digest in follows}
    oldest = min(at for at, _ in named.values())
    stored = {item_id: (at, _digest(box, body)) for item_id, at, box, body in store.edits(doc_id, oldest - 1)}
    for item_id, (at, digest) in named.items():
        now = stored.get(item_id)
        if now is None or (now[0] <= version and now != (at, digest)):
            held = "no edit" if now is None else f"another edit (version {now[0]})"
            return (
                f"it holds an edit of {item_id!r} at version {at}, the store {held}: it follows other edits"
            )
    for item_id, (at, _) in stored.items():
        if oldest < at <= version and item_id not in named:
            return (
                f"the store holds an edit of {item_id!r} at version {at}, it does not: it follows other edits"
            )
    if all(stored[item_id][0] > version for item_id in named):
        return "every edit it follows was edited again since: it cannot be checked"
    return None


def _digest(box: tuple[float, ...] | None, body: bytes | None) -> int:
    """An edit's digest, as the store holds it: its box and body (None, None: a deletion)."""
    return xxhash.xxh3_64_intdigest(msgspec.msgpack.encode([box, body]))


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
