"""Item bodies compressed a frame at a time: how a snapshot file keeps them (~3x smaller).

A file lays its items out in the tree's order (see ``snapshots.snapshot_arrays``), so the
items of one screen lie in a few consecutive frames of ``FRAME_BYTES`` (cut between items):
an answer decompresses those, ~0.3 ms for a screen, and a small cache of the frames decoded
last keeps panning from decoding them again. A pass over every item (an export, a merge)
decompresses each frame once, in order, into a ``Spill``.

Arrays: ``frames`` (the zstd frames end to end), ``at`` (where each begins, and the end),
``first`` (each frame's first item, and n) and ``offsets`` (each item's start in the bodies
as if decompressed end to end, and the end): item ``i`` of frame ``f`` is bytes
``offsets[i] - offsets[first[f]]`` on of that frame decompressed.
"""

from __future__ import annotations

import itertools
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np
import zstandard

from spatial._kernels import UNWATCHED
from spatial.quadtree import ReadWatch

from .table import STEP_BYTES, Packed, Spill, _join, _mark_rows, _take, release

__all__ = ["FRAME_BYTES", "Framed", "framed_arrays"]

FRAME_BYTES = (
    1 << 14
)  # 16 KiB: a 1M board's bodies 130 -> 44 B an item (64 KiB: 41, 4x the bytes a screen decodes)
CACHE_BYTES = 1 << 26  # decoded frames a process keeps, all documents': ~4,000, some hundred screens
LEVEL = 1  # zstd's level: faster, and no larger than 3 on frames this small


def framed_arrays(bodies: Packed, order: np.ndarray, spill: Path | None = None) -> dict[str, np.ndarray]:
    """The items of ``bodies`` at ``order`` (positions), in that order, cut into frames of about
    ``FRAME_BYTES`` (an item larger gets one of its own), each compressed: the arrays ``Framed``
    reads. Made a frame at a time, straight from ``bodies``; with ``spill``, a directory, the
    frames go to a ``Spill`` there, not to memory."""
    bodies.read_all()
    offsets = np.concatenate(([0], np.cumsum(np.diff(bodies.offsets)[order]))).astype(np.int64)
    first = _cuts(offsets)
    compress = zstandard.ZstdCompressor(level=LEVEL, write_checksum=False).compress
    at = np.zeros(len(first), np.int64)
    with Spill(spill) if spill is not None else _Memory() as out:
        for f in range(len(first) - 1):
            items = order[first[f] : first[f + 1]]
            out.write(compress(_take(bodies.array, bodies.offsets, items)[0].data))
            at[f + 1] = out.size
            if out.size // STEP_BYTES != at[f] // STEP_BYTES:
                bodies.release()  # read once: a spilled import's pages go back to the page cache
        frames = np.frombuffer(out.mapped(), np.uint8)
    return {"frames": frames, "at": at, "first": first, "offsets": offsets}


def _cuts(offsets: np.ndarray) -> np.ndarray:
    """The first item of each frame, then n: a frame ends at the first item that starts
    ``FRAME_BYTES`` or more after its own first item."""
    n = len(offsets) - 1
    first = [0]
    while first[-1] < n:
        at = int(np.searchsorted(offsets, offsets[first[-1]] + FRAME_BYTES, side="left"))
        first.append(min(n, max(first[-1] + 1, at)))
    return np.asarray(first, np.int64)


class _Memory:
    """A ``Spill``'s interface over bytes kept in memory."""

    def __init__(self) -> None:
        self._parts: list[bytes] = []
        self.size = 0

    def __enter__(self) -> _Memory:
        return self

    def __exit__(self, *_: object) -> None:
        pass

    def write(self, data: bytes) -> None:
        self._parts.append(data)
        self.size += len(data)

    def mapped(self) -> bytes:
        return b"".join(self._parts)


class Framed:
    """Item bodies kept as ``framed_arrays`` made them (mapped from a file, its reads checked
    by ``watch``): read like a ``Packed``, a frame decoded at a time."""

    def __init__(
        self,
        frames: np.ndarray,
        at: np.ndarray,
        first: np.ndarray,
        offsets: np.ndarray,
        watch: ReadWatch | None = None,
    ) -> None:
        self.frames, self.at, self.first, self.offsets = frames, at, first, offsets
        self.watch = watch
        self.places = watch.places([frames, offsets]) if watch is not None else UNWATCHED[2]
        self._key = next(_KEYS)  # its frames' in the cache
        self._index_checked = watch is None

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, i: int) -> bytes:
        self._check_rows(np.array([i], np.int64))
        f = int(np.searchsorted(self.first, i, side="right")) - 1
        base = int(self.offsets[self.first[f]])
        return self._frame(f)[int(self.offsets[i]) - base : int(self.offsets[i + 1]) - base].tobytes()

    def join(self, positions: np.ndarray, sep: bytes = b",", ends: tuple[bytes, bytes] = (b"", b"")) -> bytes:
        """``Packed.join``: the frames the items lie in decoded (or taken from the cache) and
        laid end to end, then one compiled join over them."""
        if not len(positions):
            return ends[0] + ends[1]
        self._check_rows(positions)
        frame_of = np.searchsorted(self.first, positions, side="right") - 1
        frames, which = np.unique(frame_of, return_inverse=True)
        decoded = [self._frame(f) for f in frames.tolist()]
        where = np.concatenate(([0], np.cumsum([len(d) for d in decoded])))[:-1]
        shift = (where - self.offsets[self.first[frames]])[which]
        spans = np.empty(
            2 * len(positions), np.int64
        )  # start, end of each item in ``decoded`` laid end to end
        spans[0::2] = self.offsets[positions] + shift
        spans[1::2] = self.offsets[positions + 1] + shift
        head, tail = (np.frombuffer(end, np.uint8) for end in ends)
        marks, pending, places = UNWATCHED
        steps = np.arange(0, len(spans), 2, dtype=np.int64)
        out = _join(np.concatenate(decoded), spans, steps, sep[0], head, tail, marks, pending, places)
        return out.tobytes()

    def read_all(self) -> None:
        """Before every item is read: every block of them checked."""
        if self.watch is not None:
            self.watch.check(self.frames, self.at, self.first, self.offsets)
            self._index_checked = True

    def release(self) -> None:
        release(self.frames)

    def unpacked(self, spill: Path | None = None) -> Packed:
        """The bodies decompressed end to end, each frame once (with ``spill``, a directory: into
        a ``Spill`` there, written a frame at a time)."""
        self.read_all()
        decompress = _decompressor().decompress
        frames = (decompress(self.frames[a:b].data) for a, b in zip(self.at[:-1], self.at[1:], strict=True))
        if spill is None:
            return Packed(b"".join(frames), self.offsets)
        with Spill(spill) as out:
            for k, frame in enumerate(frames):
                out.write(frame)
                if k % 1024 == 1023:
                    self.release()
            self.release()
            return Packed(out.mapped(), self.offsets)

    def take(self, order: np.ndarray, spill: Path | None = None) -> Packed:
        """``Packed.take``, from the bodies decompressed once, in order."""
        return self.unpacked(spill).take(order, spill)

    def _check_rows(self, positions: np.ndarray) -> None:
        """The offsets of the items at ``positions``, and the frames' index, checked before use."""
        watch = self.watch
        if watch is None:
            return
        if not self._index_checked:
            watch.check(self.at, self.first)
            self._index_checked = True
        if _mark_rows(positions, watch.marks, watch.pending, self.places):
            watch.settle()

    def _frame(self, f: int) -> np.ndarray:
        """Frame ``f`` decompressed: from the cache, or read (its blocks checked) and decoded."""
        key = (self._key, f)
        frame = _CACHE.get(key)
        if frame is None:
            lo, hi = self.at[f : f + 2].tolist()
            data = self.frames[lo:hi]
            if self.watch is not None:
                self.watch.check(data)
            frame = _CACHE.put(key, np.frombuffer(_decompressor().decompress(data.data), np.uint8))
        return frame


class _Cache:
    """Decoded frames of every document of the process, by (``Framed``, frame): the least
    recently used go past ``CACHE_BYTES``."""

    def __init__(self) -> None:
        self._frames: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self.bytes = 0
        self._lock = threading.Lock()

    def get(self, key: tuple[int, int]) -> np.ndarray | None:
        with self._lock:
            frame = self._frames.get(key)
            if frame is not None:
                self._frames.move_to_end(key)
            return frame

    def put(self, key: tuple[int, int], frame: np.ndarray) -> np.ndarray:
        with self._lock:
            if key in self._frames:  # another thread decoded it meanwhile
                return self._frames[key]
            self._frames[key] = frame
            self.bytes += len(frame)
            while self.bytes > CACHE_BYTES and len(self._frames) > 1:
                _, old = self._frames.popitem(last=False)
                self.bytes -= len(old)
            return frame


_CACHE = _Cache()
_KEYS = itertools.count()
_LOCAL = threading.local()


def _decompressor() -> zstandard.ZstdDecompressor:
    """This thread's decompressor (one is not safe to share, and costs ~5 us to make)."""
    made = getattr(_LOCAL, "decompressor", None)
    if made is None:
        made = _LOCAL.decompressor = zstandard.ZstdDecompressor()
    return made
