"""Finding items by their text: the items whose ``data.text`` holds every word of a query.

No index is built or stored: a compiled pass over a snapshot's packed item JSON (mapped from
its file) finds the items whose JSON holds every word, ASCII letters matched regardless of
case, and only those are decoded to check that the words are in their text. A million items'
JSON (~100 MB) is scanned in well under the 200 ms a person waits for a "go to".
"""

from __future__ import annotations

from collections.abc import Iterator

import msgspec
import numba
import numpy as np

from .snapshots import Snapshot
from .table import Packed

__all__ = ["search"]


class _Text(msgspec.Struct):
    data: dict | None = None


_text = msgspec.json.Decoder(_Text)


MAX_WORDS = 32  # words a query may hold: a bit each in the compiled pass
CHUNK = 1 << 16  # items scanned between checks: a query with early hits stops early


def search(snap: Snapshot, query: str, limit: int) -> tuple[list[int], bool]:
    """Positions of up to ``limit`` items whose text holds every word of ``query``
    (case-insensitively, by Unicode case folding), in document order; and whether there are more.

    :raises ValueError: if ``query`` has no word
    """
    words = query.casefold().split()
    if not words or len(words) > MAX_WORDS:
        raise ValueError(
            f"a query holds 1 to {MAX_WORDS} words, not {len(words)}: give some text to look for"
        )
    found: list[int] = []
    for pos in _candidates(snap, _needles(query.split())):
        if pos in snap.tree and _holds(snap.item_json(pos), words):
            if len(found) == limit:
                return found, True
            found.append(pos)
    return found, False


def _needles(words: list[str]) -> tuple[Packed, np.ndarray]:
    """What the compiled pass looks for: each word as it stands in JSON (escaped as the bodies
    were written), ASCII letters folded by the pass itself; a word with other letters in its
    lower, upper and title case, any of which will do. ``(needles, group of each)``."""
    needles, groups = [], []
    for group, word in enumerate(words):
        forms = (
            {word.lower()} if word.isascii() else {word.casefold(), word.lower(), word.upper(), word.title()}
        )
        for form in sorted(forms):
            needles.append(msgspec.json.encode(form)[1:-1])
            groups.append(group)
    return Packed.of(needles), np.array(groups, np.int64)


def _candidates(snap: Snapshot, needles: tuple[Packed, np.ndarray]) -> Iterator[int]:
    """Positions, ascending, whose JSON holds a form of every word: the table's a chunk at a
    time, then the edited items'."""
    packed, groups = needles
    wanted = (packed.array, packed.offsets, groups, int(groups.max()) + 1)
    bodies = snap.table.bodies
    buffer, edited = bodies.array, set(snap.overlay)
    for start in range(0, len(bodies), CHUNK):
        stop = min(start + CHUNK, len(bodies))
        hits = _scan(buffer, bodies.offsets[start : stop + 1], *wanted)
        for pos in (hits + start).tolist():
            if pos not in edited:
                yield pos
    for pos in sorted(edited):  # edited items' JSON is not in the table's buffer
        body = np.frombuffer(snap.item_json(pos), np.uint8)
        if len(_scan(body, np.array([0, len(body)], np.int64), *wanted)):
            yield pos


def _holds(body: bytes, words: list[str]) -> bool:
    data = _text.decode(body).data
    text = data.get("text") if isinstance(data, dict) else None
    if not isinstance(text, str):
        return False
    folded = text.casefold()
    return all(word in folded for word in words)


@numba.njit(cache=True, nogil=True, inline="always")
def _lower(c: int) -> int:  # pragma: no cover - compiled
    return c | 0x20 if 65 <= c <= 90 else c


@numba.njit(cache=True, nogil=True, inline="always")
def _holds_needle(buffer, start, stop, needles, lo, hi) -> bool:  # pragma: no cover - compiled
    size = hi - lo
    first = _lower(needles[lo])
    for j in range(start, stop - size + 1):
        if _lower(buffer[j]) != first:
            continue
        m = 1
        while m < size and _lower(buffer[j + m]) == _lower(needles[lo + m]):
            m += 1
        if m == size:
            return True
    return False


@numba.njit(cache=True, nogil=True, parallel=True)
def _scan(buffer, offsets, needles, bounds, groups, n_groups) -> np.ndarray:  # pragma: no cover
    """Items of ``offsets`` (from 0) whose bytes hold a needle of every group, ASCII letters
    compared lower-cased; the items are scanned on every core."""
    n = len(offsets) - 1
    keep = np.zeros(n, np.bool_)
    for i in numba.prange(n):
        start, stop = offsets[i], offsets[i + 1]
        met = 0  # a bit per group met
        for k in range(len(bounds) - 1):
            bit = 1 << groups[k]
            if not met & bit and _holds_needle(buffer, start, stop, needles, bounds[k], bounds[k + 1]):
                met |= bit
        keep[i] = met == (1 << n_groups) - 1
    return np.flatnonzero(keep)
