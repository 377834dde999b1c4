"""Finding text as people type it: a phrase, within one text item or across consecutive ones.

A query is folded as the document's text was (:func:`app.text.fold`: NFKC, case folding,
accents removed, typographic quotes, apostrophes and dashes made plain, white space made
single spaces) and looked for in the snapshot's :class:`~app.text.TextIndex`, one substring
search in C however many words the query has: a hit may start in one item and end in a later
one (``these first`` across two word items of a PDF's line; ``encapsulates`` across the two
pieces of a word broken at a line end). Options narrow the hits the fold found:
``case="match"`` and ``accents="match"`` compare the hit's items' own texts, folded less
(``accents="match"`` keeps quotes and dashes as typed too); ``whole="words"`` wants no letter
or digit right before or after.

A hit's ``boxes`` are one a line it covers, each the union of its items on that line: a phrase
that wraps is marked on each line, not by one box over both lines.

Hits come in document order, a page at a time; the cursor of the next page is where the
buffer search resumes, with the version it belongs to and the count the first page made.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

import numpy as np
import orjson

from .errors import Busy, Conflict, Invalid
from .snapshots import Snapshot
from .text import TextIndex, fold, piece_of, reading

__all__ = [
    "Hit",
    "MAX_QUERY_BYTES",
    "Options",
    "Page",
    "Searches",
    "TOTAL_CAP",
    "answer",
    "line_boxes",
    "search",
]

MAX_QUERY_BYTES = 1024  # a query, folded, as UTF-8
TOTAL_CAP = 10_000  # hits counted for ``total`` (a Python step each); past it, ``total`` says "at least"
T = TypeVar("T")


@dataclass(frozen=True)
class Options:
    """What a query asks beyond the fold: as PDF.js's find bar offers."""

    case: Literal["any", "match"] = "any"
    accents: Literal["any", "match"] = "any"
    whole: Literal["any", "words"] = "any"

    @property
    def strict(self) -> bool:
        return self.case == "match" or self.accents == "match"


Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class Hit:
    """One occurrence: the items it spans (positions, in order), their box, a box for each
    line they lie on (see ``line_boxes``), and their text as a reader reads it."""

    positions: list[int]
    box: Box
    boxes: list[Box]
    text: str


@dataclass(frozen=True)
class Page:
    hits: list[Hit]
    more: bool
    cursor: str | None  # the next page's, when ``more``
    total: int  # hits in the document (up to TOTAL_CAP)
    total_exact: bool


class Searches:
    """Searches run in a small pool of their own, so however many come and however long they
    take, viewports, diffs, streams and ``/health`` never wait behind them; past
    ``queue`` waiting, a search is refused with 503 rather than queued without end. One a
    worker process, made as its app starts."""

    def __init__(self, threads: int, queue: int) -> None:
        self.pool = ThreadPoolExecutor(threads, thread_name_prefix="search")
        self.room = asyncio.Semaphore(threads + queue)
        self.threads, self.queue = threads, queue

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` in the pool, once it has room.

        :raises Busy: if ``threads`` run and ``queue`` wait already
        """
        if self.room.locked():
            raise Busy(
                f"{self.threads} searches run and {self.queue} wait already (VANTAGE_SEARCH_THREADS, "
                "VANTAGE_SEARCH_QUEUE): try again in a moment"
            )
        async with self.room:
            return await asyncio.get_running_loop().run_in_executor(self.pool, fn, *args)


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


def answer(snap: Snapshot, page: Page) -> bytes:
    """``page`` as the search route's JSON: the snapshot's version, the page's counts and
    cursor, each hit's item ids, box, line boxes and text, then the hits' items, each once."""
    positions = list(dict.fromkeys(p for hit in page.hits for p in hit.positions))
    at = {p: snap.item_id(p) for p in positions}
    head = orjson.dumps(
        {
            "version": snap.version,
            "count": len(page.hits),
            "more": page.more,
            "cursor": page.cursor,
            "total": page.total,
            "total_exact": page.total_exact,
            "hits": [
                {"ids": [at[p] for p in h.positions], "box": h.box, "boxes": h.boxes, "text": h.text}
                for h in page.hits
            ],
        }
    )
    return snap.items_array(np.array(positions, np.int64), ends=(head[:-1] + b',"items":[', b"]}"))


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
        pieces = [piece_of(snap.item_json(int(p))) for p in index.positions[index.items(start, end)]]
        folded = fold(reading(pieces), case=options.case == "match", accents=options.accents == "match")
        return strict in folded
    return True


def _hit(snap: Snapshot, index: TextIndex, hit: tuple[int, int]) -> Hit:
    positions = [int(p) for p in index.positions[index.items(*hit)]]
    boxes: list[Box] = [
        (float(b[0]), float(b[1]), float(b[2]), float(b[3])) for b in map(snap.tree.get, positions)
    ]
    lines = line_boxes(boxes)
    box = (
        min(b[0] for b in lines),
        min(b[1] for b in lines),
        max(b[2] for b in lines),
        max(b[3] for b in lines),
    )
    return Hit(positions, box, lines, reading(piece_of(snap.item_json(p)) for p in positions))


def line_boxes(boxes: list[Box]) -> list[Box]:
    """Consecutive items' boxes (in reading order) as one box a line: the union of a run of
    items on one line, a new box where an item starts a new line (it does not lie beside the
    one before, at least half the height of the lower of the two in common, to its right).

    >>> line_boxes([(0, 0, 5, 10), (6, 1, 9, 10), (0, 12, 4, 22), (5, 12, 8, 22)])
    [(0, 0, 9, 10), (0, 12, 8, 22)]
    """
    out: list[Box] = []
    x0, y0, x1, y1 = boxes[0]
    last = boxes[0]
    for b in boxes[1:]:
        common = min(last[3], b[3]) - max(last[1], b[1])
        if b[0] >= last[0] and common >= 0.5 * min(last[3] - last[1], b[3] - b[1]):
            x0, y0, x1, y1 = min(x0, b[0]), min(y0, b[1]), max(x1, b[2]), max(y1, b[3])
        else:
            out.append((x0, y0, x1, y1))
            x0, y0, x1, y1 = b
        last = b
    out.append((x0, y0, x1, y1))
    return out
