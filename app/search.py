"""Finding text as people type it: a phrase, within one text item or across consecutive ones.

A query is folded as the document's text was (:func:`app.text.fold`: NFKC, case folding,
accents removed, white space made single spaces) and looked for in the snapshot's
:class:`~app.text.TextIndex`, one substring search in C however many words the query has: a
hit may start in one item and end in a later one (``these first`` across two word items of a
PDF's line). Options narrow the hits the fold found: ``case="match"`` and ``accents="match"``
compare the hit's items' own texts, folded less; ``whole="words"`` wants no letter or digit
right before or after.

Hits come in document order, a page at a time; the cursor of the next page is where the
buffer search resumes, with the version it belongs to and the count the first page made.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .errors import Conflict, Invalid
from .snapshots import Snapshot
from .text import TextIndex, fold, text_of

__all__ = ["MAX_QUERY_BYTES", "TOTAL_CAP", "Hit", "Options", "Page", "search"]

MAX_QUERY_BYTES = 1024  # a query, folded, as UTF-8
TOTAL_CAP = 10_000  # hits counted for ``total`` (a Python step each); past it, ``total`` says "at least"


@dataclass(frozen=True)
class Options:
    """What a query asks beyond the fold: as PDF.js's find bar offers."""

    case: Literal["any", "match"] = "any"
    accents: Literal["any", "match"] = "any"
    whole: Literal["any", "words"] = "any"

    @property
    def strict(self) -> bool:
        return self.case == "match" or self.accents == "match"


@dataclass(frozen=True)
class Hit:
    """One occurrence: the items it spans (positions, in order), their box, and their text."""

    positions: list[int]
    box: tuple[float, float, float, float]
    text: str


@dataclass(frozen=True)
class Page:
    hits: list[Hit]
    more: bool
    cursor: str | None  # the next page's, when ``more``
    total: int  # hits in the document (up to TOTAL_CAP)
    total_exact: bool


def search(
    snap: Snapshot, query: str, limit: int, cursor: str | None = None, options: Options = Options()
) -> Page:
    """A page of up to ``limit`` hits of ``query`` in ``snap``, from ``cursor`` (the one the
    page before gave) or the start.

    Cost: one substring search of the folded text, which the first page goes on with to
    count the hits (up to TOTAL_CAP; later pages carry the count in their cursor); a few
    microseconds a hit for its items, boxes and checks.

    :raises Invalid: if ``query`` folds to nothing, or to more than MAX_QUERY_BYTES, or the
        cursor is not one this search gave
    :raises Conflict: if the cursor is of another version of the document: search again
    """
    needle = fold(query).encode()
    if not needle:
        raise Invalid("q: give some text to look for (a word, or a phrase)")
    if len(needle) > MAX_QUERY_BYTES:
        raise Invalid(f"q: {len(needle)} bytes once folded; a query holds at most {MAX_QUERY_BYTES}")
    start, counted = _start(cursor, snap.version)
    index = snap.search_index
    strict = fold(query, case=options.case == "match", accents=options.accents == "match")
    hits = (h for h in index.find(needle, start) if _kept(snap, index, h, strict, options))
    page = list(itertools.islice(hits, limit + 1))
    more = len(page) > limit
    if counted is None:  # the first page: the same pass goes on to count the rest, up to the cap
        counted = len(page) + (
            sum(1 for _ in itertools.islice(hits, TOTAL_CAP + 1 - len(page))) if more else 0
        )
    page = page[:limit]
    return Page(
        [_hit(snap, index, h) for h in page],
        more,
        f"{snap.version}.{page[-1][1]}.{counted}" if more else None,
        min(counted, TOTAL_CAP),
        counted <= TOTAL_CAP,
    )


def _start(cursor: str | None, version: int) -> tuple[int, int | None]:
    """Where a page's search starts, and the hits counted on the first page (None: count now)."""
    if cursor is None:
        return 0, None
    parts = cursor.split(".")
    if len(parts) != 3 or not all(p.isdigit() for p in parts):
        raise Invalid(f"cursor={cursor[:40]!r}: not a cursor a search gave; leave it out to start over")
    if int(parts[0]) != version:
        raise Conflict(f"cursor={cursor}: of version {parts[0]}, the document is at {version}: search again")
    return int(parts[1]), int(parts[2])


def _kept(snap: Snapshot, index: TextIndex, hit: tuple[int, int], strict: str, options: Options) -> bool:
    """Whether a hit of the fold is one the options keep."""
    start, end = hit
    if options.whole == "words":
        before = bytes(index.text[max(0, start - 4) : start]).decode(errors="ignore")[-1:]
        after = bytes(index.text[end : end + 4]).decode(errors="ignore")[:1]
        if (before and before.isalnum()) or (after and after.isalnum()):
            return False
    if options.strict:
        texts = [text_of(snap.item_json(int(p))) or "" for p in index.positions[index.items(start, end)]]
        folded = fold(" ".join(texts), case=options.case == "match", accents=options.accents == "match")
        return strict in folded
    return True


def _hit(snap: Snapshot, index: TextIndex, hit: tuple[int, int]) -> Hit:
    positions = [int(p) for p in index.positions[index.items(*hit)]]
    boxes = np.array([snap.tree.get(p) for p in positions])
    box = (
        float(boxes[:, 0].min()),
        float(boxes[:, 1].min()),
        float(boxes[:, 2].max()),
        float(boxes[:, 3].max()),
    )
    text = " ".join(text_of(snap.item_json(p)) or "" for p in positions)
    return Hit(positions, box, text)
