"""A document's text, folded as people search it and laid end to end, for phrase search.

Every item whose ``data.text`` holds something is a *text item*. Folded (Unicode NFKC, so
ligatures such as ``ﬁ`` and full-width forms become plain letters; case folding, so ``ß``
is ``ss``; accents removed; typographic quotes, apostrophes and dashes made the ones a
keyboard types; soft hyphens and other invisible marks dropped; white space runs made one
space), the text items' texts are joined in document order (table position: the import's
order, words of a line, lines of a page), each followed by one space, into one UTF-8 buffer.
A phrase is then one substring search of that buffer, however many words it has, and may run
across items: ``these first`` finds the word ``these`` followed by the item ``first``.
``starts`` maps a byte of the buffer to its item.

An item's ``data.join`` says the next text item goes on with the same word: ``"word"``, with
no space between them (``2008-`` then ``02``); ``"hyphen"``, the same with this item's
trailing hyphen dropped (``encap-`` then ``sulates`` reads ``encapsulates``: a word broken at
a line end, each piece drawn on its own line). The PDF importer sets it; any item may.

The buffer and its two arrays are built with the base's snapshot and saved in its file, so a
search maps them rather than reading a million items' JSON; edits are laid over them when a
search first needs them (:meth:`TextIndex.with_edits`).
"""

from __future__ import annotations

import itertools
import re
import time
import unicodedata
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from .packed import STEP_BYTES, Packed

__all__ = ["FIND_BLOCK", "JOINS", "Piece", "TextIndex", "entry", "fold", "piece_of", "reading"]

SLICE = 65_536  # items folded, joined and encoded at a time: list speed, short holds of the lock
FIND_BLOCK = 1 << 20  # bytes searched while holding the interpreter's lock, at most (~0.3 ms)


JOINS = ("word", "hyphen")  # the values of ``data.join``: see the module's docstring


class _Data(msgspec.Struct):
    text: Any = None
    join: Any = None


class _Item(msgspec.Struct):  # only what search reads: no dict is made for ``data``
    data: _Data | None = None


_decode = msgspec.json.Decoder(_Item).decode


_DATA = re.compile(rb'"data":')  # the key as items are stored (encoded compactly); inside a
# string a quote is escaped, so a match is the key, or (harmless) a string ending in "data"


def _with_data(bodies: Packed) -> np.ndarray:
    """The positions of the items whose JSON holds a ``data`` object, ascending, found by one
    search of the packed buffer in C (in blocks: the lock is let go between them)."""
    found: list[np.ndarray] = []
    buffer, step = bodies.buffer, STEP_BYTES
    for start in range(0, len(buffer), step):
        block = buffer[start : start + step + 6]  # a key across the block's end is found in this one
        hits = np.fromiter((m.start() + start for m in _DATA.finditer(block)), np.int64)
        found.append(hits[hits < start + step])
        bodies.release()  # a spilled import's pages go back as they are read
    places = (
        np.searchsorted(bodies.offsets, np.concatenate(found or [np.empty(0, np.int64)]), side="right") - 1
    )
    return np.unique(places)


Piece = tuple[str | None, str | None]  # an item's text and how it joins the next: ``piece_of``


def _texts(bodies: Packed, with_data: np.ndarray) -> Iterator[tuple[list[int], list[Piece]]]:
    """``(positions, their pieces)`` of the items at ``with_data`` (ascending), a slice at a
    time, read a step of ``bodies`` at a time (see ``Packed.steps``)."""
    for lo, hi in bodies.steps():
        step = with_data[np.searchsorted(with_data, lo) : np.searchsorted(with_data, hi)]
        for start in range(0, len(step), SLICE):
            part = step[start : start + SLICE].tolist()
            yield part, [piece_of(bodies[p]) for p in part]


def piece_of(body: bytes | memoryview) -> Piece:
    """An item's ``data.text`` (None when it has none) and its ``data.join`` (None unless one
    of ``JOINS``), from its JSON."""
    data = _decode(body).data
    if data is None:
        return None, None
    text, join = data.text, data.join
    return (text if isinstance(text, str) else None), (join if join in JOINS else None)


def entry(text: str | None, join: str | None = None) -> str:
    """An item's text as the index holds it: folded, then a space, or nothing where ``join``
    says the next item goes on with the same word ("hyphen": its trailing hyphen dropped).
    Empty when the text folds to nothing.

    >>> entry("Quarterly"), entry("encap-", "hyphen"), entry("2008-", "word"), entry("  ")
    ('quarterly ', 'encap', '2008-', '')
    """
    folded = fold(text) if text else ""
    if not folded or join is None:
        return folded and folded + " "
    return folded[:-1] if join == "hyphen" and folded.endswith("-") else folded


def reading(pieces: Iterable[Piece]) -> str:
    """Consecutive items' texts as a reader reads them: a space between two, none where the
    first joins the next (its line-end hyphen dropped for "hyphen").

    >>> reading([("these", None), ("encap-", "hyphen"), ("sulates", None), ("2008-", "word"), ("02", None)])
    'these encapsulates 2008-02'
    """
    out: list[str] = []
    for text, join in pieces:
        text = " ".join((text or "").split())
        if not text:
            continue
        if join == "hyphen" and text[-1] in _HYPHENS:
            out.append(text[:-1])
        else:
            out.append(text if join else text + " ")
    return "".join(out).rstrip()


# Typographic quotes, apostrophes and dashes as a keyboard types them (folded with accents:
# ``accents="match"`` keeps them as typed), and marks no one types or sees (always dropped):
# the soft hyphen, zero-width space, word joiner, byte order mark, and U+FFFE (a noncharacter
# PDFium puts where a line-end hyphen was).
_TYPED = str.maketrans(
    {
        **dict.fromkeys("‘’‚‛′ʼ", "'"),
        **dict.fromkeys("“”„‟″", '"'),
        **dict.fromkeys("‐‑‒–—―−", "-"),
    }
)
_UNSEEN = str.maketrans(dict.fromkeys("\u00ad\u200b\u2060\ufeff\ufffe"))
_HYPHENS = "-\u2010\u00ad\ufffe"  # what may end a word broken at a line end


def fold(text: str, *, case: bool = False, accents: bool = False) -> str:
    """``text`` as search compares it: NFKC, then case folded unless ``case``, accents
    removed and typographic quotes, apostrophes and dashes made plain unless ``accents``,
    invisible marks (soft hyphens) dropped, white space runs made one space, stripped.

    >>> fold("  ﬁnancial   Straße  "), fold("éÉté"), fold("Ｆｕｌｌ"), fold("Été", case=True)
    ('financial strasse', 'eete', 'full', 'Ete')
    >>> print(fold("It’s “soft” hy\\u00adphens – dashes"), fold("It’s", accents=True))
    it's "soft" hyphens - dashes it’s
    """
    if text.isascii():  # most text: nothing for NFKC, accents or typography to do
        return " ".join((text if case else text.lower()).split())
    text = unicodedata.normalize("NFKC", text).translate(_UNSEEN)
    if not case:
        text = text.casefold()
    if not accents:
        decomposed = unicodedata.normalize("NFKD", text)
        text = unicodedata.normalize("NFC", "".join(c for c in decomposed if not unicodedata.combining(c)))
        text = text.translate(_TYPED)
    return " ".join(text.split())


@dataclass(frozen=True)
class TextIndex:
    """The folded texts of a document's text items, end to end.

    ``text``: the UTF-8 buffer, each item's folded text followed by one space (or none, where
    the item joins the next: see ``entry``); ``starts``:
    where each item's text begins in it, and its end (n + 1 offsets); ``positions``: each
    item's table position, in document order (ascending, unless a snapshot file laid the
    items out in its tree's order).
    """

    text: np.ndarray  # uint8
    starts: np.ndarray  # int64, n + 1
    positions: np.ndarray  # int64, n

    @classmethod
    def build(cls, texts: Iterable[tuple[int, str | None] | tuple[int, str | None, str | None]]) -> TextIndex:
        """The index of ``(position, text)`` pairs or ``(position, text, join)`` triples,
        positions ascending; items whose text folds to nothing are left out."""
        rows = iter(texts)
        slices = iter(lambda: list(itertools.islice(rows, SLICE)), [])
        return cls._of_slices(
            ([r[0] for r in s], [(r[1], r[2] if len(r) > 2 else None) for r in s]) for s in slices
        )

    @classmethod
    def of_table(cls, bodies: Packed) -> TextIndex:
        """The index of a table's item JSON (``ItemTable.bodies``), in table order.

        Cost: one JSON decode an item with ``data`` (~0.25 us: only ``data.text`` is made an
        object), none for the others (found by one search of the buffer), one fold a text item
        (~0.1 us when ASCII)."""
        return cls._of_slices(_texts(bodies, _with_data(bodies)))

    @classmethod
    def _of_slices(cls, slices: Iterable[tuple[Sequence[int], list[Piece]]]) -> TextIndex:
        """Folded, joined and encoded a slice of items at a time, then copied into one buffer a
        slice at a time: no single step holds the interpreter's lock for long, however large
        the document's text (an import beside other requests), and lists run at list speed."""
        parts: list[bytes] = []
        positions: list[np.ndarray] = []
        sizes: list[np.ndarray] = []
        for where, pieces in slices:
            if any(join for _, join in pieces):  # a word across items: each item's own entry
                entries = [(pos, e) for pos, piece in zip(where, pieces, strict=True) if (e := entry(*piece))]
                words, spaced = [e for _, e in entries], 0
            else:  # the common slice: a space after each, in one join
                entries = [
                    (pos, f) for pos, (t, _) in zip(where, pieces, strict=True) if t and (f := fold(t))
                ]
                words, spaced = [f for _, f in entries], 1
            if not entries:
                continue
            joined = (" " if spaced else "").join(words) + " " * spaced
            lengths = map(len, words) if joined.isascii() else (len(f.encode()) for f in words)
            parts.append(joined.encode())
            sizes.append(np.fromiter(lengths, np.int64, len(words)) + spaced)
            positions.append(np.fromiter((pos for pos, _ in entries), np.int64, len(entries)))
        buffer = np.empty(sum(map(len, parts)), np.uint8)
        at = 0
        for part in parts:
            buffer[at : at + len(part)] = np.frombuffer(part, np.uint8)
            at += len(part)
        starts = np.concatenate(([0], np.cumsum(np.concatenate(sizes)))) if sizes else np.zeros(1)
        return cls(
            buffer, starts.astype(np.int64), np.concatenate(positions) if positions else np.empty(0, np.int64)
        )

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"text": self.text, "starts": self.starts, "positions": self.positions}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> TextIndex:
        return cls(arrays["text"], arrays["starts"], arrays["positions"])

    @property
    def nbytes(self) -> int:
        return self.text.nbytes + self.starts.nbytes + self.positions.nbytes

    def items(self, start: int, end: int) -> slice:
        """The items (indices into ``positions``) that bytes ``start:end`` of the buffer lie in."""
        first = int(np.searchsorted(self.starts, start, "right")) - 1
        last = int(np.searchsorted(self.starts, end - 1, "right")) - 1
        return slice(first, last + 1)

    def with_edits(
        self, changed: dict[int, Piece], deleted: Iterable[int], place: Callable[[int], int] = int
    ) -> TextIndex:
        """This index with the items at ``changed``'s positions given those pieces (text and
        join; a None text: no text) and the items at ``deleted`` gone; every item stays in
        document order (an edited item where it was, a new one at its new position, after the
        table's), where ``place(position)`` says a position comes in it (the position itself,
        by default).

        Cost: O(n) in C (a mask over the positions, one copy of the buffer in as many slices
        as there are runs between edits), plus a fold for each changed text."""
        gone = np.fromiter(sorted({*changed, *deleted}), np.int64)
        keep = ~np.isin(self.positions, gone)
        edges = np.flatnonzero(np.diff(np.concatenate(([0], keep.view(np.int8), [0])))).reshape(-1, 2)
        pieces: list[tuple[int, int, int, int | bytes]] = [
            (place(int(self.positions[a])), -1, a, b) for a, b in edges.tolist()
        ]
        for pos, piece in changed.items():
            folded = entry(*piece).encode()
            if folded:
                pieces.append((place(pos), pos, -1, folded))
        pieces.sort()
        parts, starts, positions, at = [], [], [], 0
        for _, pos, a, b in pieces:
            if isinstance(b, bytes):  # an edited item's text, with what follows it
                parts.append(b)
                starts.append(np.array([at], np.int64))
                positions.append(np.array([pos], np.int64))
                at += len(b)
            else:  # a run of items kept as they were
                lo, hi = int(self.starts[a]), int(self.starts[b])
                parts.append(self.text[lo:hi].tobytes())
                starts.append(self.starts[a:b] - lo + at)
                positions.append(self.positions[a:b])
                at += hi - lo
        starts.append(np.array([at], np.int64))
        return TextIndex(
            np.frombuffer(b"".join(parts), np.uint8),
            np.concatenate(starts),
            np.concatenate(positions) if positions else np.empty(0, np.int64),
        )

    def find(self, needle: bytes, start: int = 0) -> Iterator[tuple[int, int]]:
        """``(start, end)`` of each occurrence of ``needle`` from byte ``start`` on, not
        overlapping, in order: one pass over the buffer in C, a block at a time, the
        interpreter's lock let go between blocks (viewports go on while a search runs)."""
        pattern, text = re.compile(re.escape(needle)), self.text.data  # a memoryview of it
        at, size = start, len(text)
        while at < size:
            block = min(size, at + FIND_BLOCK)
            for found in pattern.finditer(text, at, min(size, block + len(needle) - 1)):
                if found.start() >= block:  # the next block's: it is found again there
                    break
                yield found.start(), found.end()
                at = found.end()
            at = max(at, block)
            time.sleep(0)  # let go of the interpreter's lock: a waiting request takes it now, not in 5 ms
