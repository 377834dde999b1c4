"""Every answer a client gets is built here, from one snapshot: the items in a viewport, and
what changed for a panning client (the HTTP ``diff`` and each step of the stream).

Moving the view is the index's ``diff``; items edited since the version the client holds are
patched on top from the snapshot's change log, so a client never keeps a stale box. No answer
lists more than its cap of items or ids: past it, ``truncated`` says so, and a move whose
``leave`` would pass it becomes a ``reset``.

The HTTP answers, for validated parameters, are here too: :func:`viewport_answer`,
:func:`diff_answer` and :func:`tile_answered`. Their routes (``app.routers``) and the fast
path (``app.hot``) both call them, so the two answer alike.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple, cast

import msgspec
import numpy as np
import orjson
from fastapi.concurrency import run_in_threadpool

from spatial.rect import Rect, RectLike, as_rect, touches

from .config import Settings
from .documents import Document
from .errors import Conflict, Invalid, NotFound
from .looks import agg_id, parse_agg_id
from .masks import Grid, grid_of, masks
from .snapshots import Snapshot
from .tiles import (
    LADDER_STEPS,
    MAX_DEPTH,
    MAX_HEIGHT,
    TILE_PIXELS,
    TileKey,
    Tiles,
    ladder_level,
    tile_changed_since,
    tiles_over,
    within_reach,
)

__all__ = [
    "Change",
    "Held",
    "IMMUTABLE",
    "SCREEN",
    "Shown",
    "View",
    "change",
    "diff_answer",
    "min_size_for",
    "shown",
    "tile_answered",
    "view_of",
    "viewport",
    "viewport_answer",
]

_NONE = np.empty(0, np.int64)
SCREEN = 1920 * 1080  # the screen an entry budget is given for
IMMUTABLE = "max-age=31536000, immutable"  # a tile asked at a version: its URL never changes


def min_size_for(scale: float | None, min_px: float) -> float:
    """Canvas units below which an item is under ``min_px`` on screen (0: keep everything).
    An overflow (a tiny scale) means no finite item is big enough: the largest float says so."""
    return min(min_px / scale, sys.float_info.max) if scale and min_px else 0.0


class View(NamedTuple):
    """A viewport and its level of detail: items whose larger side is under ``min_size`` are
    too small to draw; ``pixels`` is the screen area it covers (for the entry budget). A
    tuple: one is made per request, and a frozen dataclass costs three times as much."""

    rect: Rect
    min_size: float = 0.0
    pixels: float | None = None
    scale: float | None = None  # screen pixels a unit: aggregates' masks are drawn at it

    @classmethod
    def of(cls, rect: object, name: str, scale: float | None = None, min_px: float = 0.0) -> View:
        """:raises ValueError: naming ``name`` when the rect is not finite or is inverted"""
        r = as_rect(cast(RectLike, rect), name)  # as_rect checks any object: four numbers or ValueError
        pixels = (r[2] - r[0]) * (r[3] - r[1]) * scale * scale if scale else None
        return cls(r, min_size_for(scale, min_px), pixels, scale)

    @property
    def grid(self) -> Grid | None:
        """The pixel grid of the screen this viewport fills."""
        return grid_of((self.rect[0], self.rect[1]), self.scale)


class Shown(NamedTuple):
    """What a client is shown for a view: the items of at least ``size`` touching ``rect``, and
    ``band``'s aggregates touching it standing in for the smaller ones (None: no aggregates)."""

    rect: Rect
    size: float
    band: int | None
    grid: Grid | None = None  # the screen's pixel grid the aggregates' masks were made in

    def shows(self, box: Rect) -> bool:
        return touches(box, self.rect) and max(box[2] - box[0], box[3] - box[1]) >= self.size


def shown(snap: Snapshot, view: View, cap: int, budget: float | None = None) -> Shown:
    """How ``snap`` answers ``view``: at the band its level of detail asks for, or a coarser
    one when that band's items and aggregates would be more than ``cap`` or than ``budget``
    entries per full-HD screen of ``view.pixels``. Without level of detail: exact, no band."""
    return _choose(snap, view, cap, budget)[0]


def _choose(
    snap: Snapshot, view: View, cap: int, budget: float | None
) -> tuple[Shown, np.ndarray | None, np.ndarray]:
    """``shown``, with the items and aggregates it shows when choosing the band found them
    (items None: not looked up yet)."""
    overview = snap.overview
    most = cap if budget is None or view.pixels is None else min(cap, max(1, budget * view.pixels / SCREEN))
    choice = overview.choose(snap.tree, view.rect, view.min_size, most) if overview is not None else None
    if choice is None:
        return Shown(view.rect, view.min_size, None), None, _NONE
    assert overview is not None  # a choice comes from the overview
    band, items, aggregates = choice
    return Shown(view.rect, overview.threshold(band), band, view.grid), items, aggregates


@dataclass(frozen=True)
class Held:
    """What a client holds: ``shown`` as of ``version``. ``snapshot`` is that version itself
    when the server knows it (the stream): then only items the client was shown leave. Without
    it (a stateless diff), every edited item not shown now is listed in ``leave``, a no-op for
    ids the client does not hold."""

    shown: Shown
    version: int
    snapshot: Snapshot | None = None


class Change(NamedTuple):
    """What a client must change: ``leave`` and ``enter`` as JSON arrays, and the counts."""

    version: int
    shown: Shown  # what the client is shown once it applied this
    reset: bool  # drop everything first
    entered: int  # items and aggregates entering, before the cap
    truncated: bool  # enter was cut at the cap: the client's set is incomplete
    leave: bytes
    enter: bytes
    tiles: bytes | None = None  # a tiled answer's tiles (JSON; null zoomed in); None: not tiled

    @property
    def empty(self) -> bool:
        return not self.reset and self.leave == b"[]" and self.enter == b"[]"

    def json(self, **head: object) -> bytes:
        """The answer, with ``head`` (a stream's ``type`` and ``seq``) first."""
        fields = orjson.dumps(
            {
                **head,
                "version": self.version,
                "band": self.shown.band,
                "reset": self.reset,
                "entered": self.entered,
                "truncated": self.truncated,
            }
        )
        if self.tiles is not None:
            fields = fields[:-1] + b',"tiles":' + self.tiles + b"}"
        return fields[:-1] + b',"leave":' + self.leave + b',"enter":' + self.enter + b"}"


def viewport(
    snap: Snapshot,
    view: View,
    cap: int,
    budget: float | None = None,
    tiles: Tiles | None = None,
    tiled: bool = False,
) -> bytes:
    """The ``/viewport`` answer: what ``view`` shows, at most ``cap`` entries, aggregates first;
    how many items are shown and how many more stand in aggregates or were left out. With
    ``tiles``, masks are kept there for the next answer of the same grid; ``tiled``, the
    aggregates are left to the tiles the answer names (``tiles``), which the client fetches."""
    show, found, aggs = _choose(snap, view, cap, budget)
    if found is None:
        found = snap.tree.query(show.rect, min_size=show.size)
    omitted = len(snap.tree.query(view.rect)) - len(found) if view.min_size else 0
    fields: dict[str, object] = {
        "version": snap.version,
        "band": show.band,
        "count": len(found),
        "aggregates": len(aggs),
        "omitted_small": omitted,
        "truncated": len(found) + (0 if tiled else len(aggs)) > cap,
    }
    if tiled:
        fields["tiles"] = tiles_of(show, aggs)
        aggs = _NONE
    head = orjson.dumps(fields)
    return _entries(snap, show.band, found, aggs, cap, view, tiles, ends=(head[:-1] + b',"items":[', b"]}"))


def tiles_of(show: Shown, aggs: np.ndarray) -> dict[str, object] | None:
    """The tiles holding ``aggs``, the aggregates ``show`` shows: its band, the ladder level
    nearest its scale, the tiles' size in pixels and the inclusive range of their columns and
    rows; None when it shows none."""
    if show.band is None or show.grid is None or not len(aggs):
        return None
    z = ladder_level(show.grid[0])
    return {"band": show.band, "z": z, "size": TILE_PIXELS, "range": tiles_over(show.band, z, show.rect)}


def change(
    snap: Snapshot,
    new: View,
    held: Held | None,
    cap: int,
    budget: float | None = None,
    tiles: Tiles | None = None,
    tiled: bool = False,
) -> Change:
    """What a client holding ``held`` needs to show ``new`` at ``snap``.

    Without ``held``, when the change log no longer reaches back to its version (an import
    since), or when more than ``cap`` ids would leave, the answer is a ``reset``: drop
    everything, then take ``enter``.

    :raises ValueError: if ``held.version`` is newer than ``snap``
    """
    show, found, aggs = _choose(snap, new, cap, budget)
    edited = snap.edited_since(held.version) if held is not None else None
    sheet = orjson.dumps(tiles_of(show, aggs)) if tiled else None
    if tiled:
        aggs = _NONE  # the client takes them from the tiles
    if held is None or edited is None or not _same_overview(snap, held):
        return _reset(snap, show, cap, new, tiles, found, aggs, sheet)
    old = held.shown
    entered, leaving = snap.tree.diff(old.rect, show.rect, min_size=(old.size, show.size))
    if tiled:  # aggregates are in tiles, never in answers: none enter or leave here
        agg_in = agg_out = _NONE
        edited = [e for e in edited if parse_agg_id(e) is None]
    else:
        agg_in, agg_out = _agg_diff(snap, old, show)
        if show.band is not None and old.band == show.band and old.grid != show.grid:
            agg_in = _aggregates(snap, show.band, show.rect)  # masks made anew: those held are replaced
    gone: list[bytes] = []  # JSON ids of edited items and aggregates that left
    if edited:
        entered, agg_in, gone = _patch(snap, edited, entered, leaving, agg_in, agg_out, show, held)
    left = len(leaving) + len(agg_out) + len(gone)
    if left > cap:  # too many ids to list: the client starts over instead
        return _reset(snap, show, cap, new, tiles, found, aggs, sheet)
    # aggregates leave only a band: agg_out is empty when old.band is None
    more = [f'"{agg_id((old.band, k))}"'.encode() for k in agg_out.tolist()] if old.band is not None else []
    count = len(entered) + len(agg_in)
    return Change(
        snap.version,
        show,
        False,
        count,
        count > cap,
        snap.ids_array(leaving, [*more, *gone]),
        _entries(snap, show.band, entered, agg_in, cap, new, tiles),
        sheet,
    )


def view_of(rect: object, name: str, scale: float | None = None, min_px: float = 0.0) -> View:
    """``View.of``, its ``ValueError`` as a 422 that says which coordinate is wrong.

    :raises Invalid: naming ``name`` when the rect is not finite or is inverted
    """
    try:
        return View.of(rect, name, scale, min_px)
    except ValueError as error:
        raise Invalid(str(error)) from None


def viewport_answer(
    doc: Document,
    settings: Settings,
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    scale: float | None = None,
    min_px: float = 0.0,
    limit: int | None = None,
    tiles: bool = False,
) -> bytes:
    """The ``/viewport`` answer for validated parameters; zoomed out (a level of detail), one
    answer shared by every client asking the same (``Tiles.answer``).

    :raises ServiceError: as the route answers it
    """
    view = view_of((x0, y0, x1, y1), "viewport", scale, min_px)
    snap, cap, budget = doc.snapshot, settings.cap(limit), settings.lod_budget
    make = partial(viewport, snap, view, cap, budget, doc.tiles, tiles)
    if not view.min_size:
        return make()
    return doc.tiles.answer(snap, (view, cap, budget, tiles), make, small=tiles)  # zoomed out: shared


def diff_answer(
    doc: Document,
    settings: Settings,
    from_: str,
    to: str,
    scale: float | None = None,
    min_px: float = 0.0,
    limit: int | None = None,
    from_scale: float | None = None,
    since: int | None = None,
    from_band: int | None = None,
    tiles: bool = False,
) -> bytes:
    """The ``/diff`` answer for validated parameters: the old viewport's ``Shown`` (at
    ``from_band``, or the band it would get now), then ``change``.

    :raises ServiceError: as the route answers it
    """
    old = view_of(from_.split(","), "from", from_scale or scale, min_px)
    new = view_of(to.split(","), "to", scale, min_px)
    snap: Snapshot = doc.snapshot
    if since is not None and since > snap.version:
        raise Conflict(f"since={since} is newer than the document's version {snap.version}")
    cap = settings.cap(limit)
    if from_band is None:
        old_shown = shown(snap, old, cap, settings.lod_budget)
    elif snap.overview is None or not old.min_size:
        raise Invalid(
            f"from_band={from_band}, but the old viewport has no level of detail (from_scale, min_px)"
        )
    else:
        band = min(max(from_band, snap.overview.lo), snap.overview.hi)
        old_shown = Shown(old.rect, snap.overview.threshold(band), band, old.grid)
    held = Held(old_shown, snap.version if since is None else since)  # without since: no edits to carry
    return change(snap, new, held, cap, settings.lod_budget, doc.tiles, tiles).json()


async def tile_answered(
    doc: Document,
    private: bool,
    band: int,
    z: int,
    tx: int,
    ty: int,
    version: int | None,
    if_none_match: str,
    accept_encoding: str,
) -> tuple[int, list[tuple[str, str]], bytes]:
    """The tile URL's answer for validated parameters, as ``(status, headers, body)``: the
    route and the fast path (:mod:`app.hot`) send it as it is. A tile made already is a
    lookup, answered here; one to make (milliseconds) is made in a worker thread.

    :raises ServiceError: a band or level the document has not, a tile out of reach, or one an
        edit after ``version`` changed (409)
    """
    snap: Snapshot = doc.snapshot
    key = _tile_key(snap, band, z, tx, ty)
    if version is not None and version < snap.version and tile_changed_since(snap, key, version):
        raise Conflict(
            f"tile {band}/{z}/{tx}/{ty} changed after version {version}: ask at version {snap.version}"
        )
    tile = doc.tiles.kept(snap, key)
    if tile is None:
        tile = await run_in_threadpool(doc.tiles.tile, snap, key)
    cache = IMMUTABLE if version is not None else "no-cache"
    headers = [
        ("etag", tile.etag),
        ("cache-control", f"{'private' if private else 'public'}, {cache}"),
        ("vary", "Accept-Encoding"),
    ]
    held = _etags(if_none_match)
    if tile.etag in held or "*" in held:
        return 304, headers, b""
    body = tile.body
    if "gzip" in accept_encoding:
        headers.append(("content-encoding", "gzip"))
        body = tile.gzipped
    return 200, [*headers, ("content-length", str(len(body))), ("content-type", "application/json")], body


def _reset(
    snap: Snapshot,
    show: Shown,
    cap: int,
    view: View,
    tiles: Tiles | None,
    entered: np.ndarray | None = None,
    aggs: np.ndarray | None = None,
    sheet: bytes | None = None,
) -> Change:
    """Everything ``show`` shows, to start over with (``entered`` and ``aggs``: found already;
    ``sheet``: a tiled answer's ``tiles``)."""
    if entered is None:
        entered = snap.tree.query(show.rect, min_size=show.size)
    if aggs is None:
        aggs = _aggregates(snap, show.band, show.rect)
    count = len(entered) + len(aggs)
    return Change(
        snap.version,
        show,
        True,
        count,
        count > cap,
        b"[]",
        _entries(snap, show.band, entered, aggs, cap, view, tiles),
        sheet,
    )


def _aggregates(snap: Snapshot, band: int | None, rect: Rect) -> np.ndarray:
    """``band``'s aggregates touching ``rect``: none without a band."""
    return _NONE if band is None or snap.overview is None else snap.overview.query(band, rect)


def _entries(
    snap: Snapshot,
    band: int | None,
    items: np.ndarray,
    aggs: np.ndarray,
    cap: int,
    view: View,
    tiles: Tiles | None,
    ends: tuple[bytes, bytes] = (b"[", b"]"),
) -> bytes:
    """The JSON array of at most ``cap`` entries: the aggregates first, then the items
    (``ends``: the array's brackets and what comes around them), each aggregate with its mask
    in ``view``'s pixels (kept in ``tiles`` for the next answer of that grid)."""
    aggs = aggs[:cap]
    grid = view.grid
    shapes = None
    if band is not None and len(aggs) and grid:
        make = masks if tiles is None else tiles.masks  # kept for the next answer of that grid
        shapes = make(snap, band, aggs, grid)
    return snap.entries_array(items[: cap - len(aggs)], band, aggs, ends, shapes)


def _same_overview(snap: Snapshot, held: Held) -> bool:
    """Whether the aggregates ``held`` shows are still numbered as in ``snap`` (an import renumbers
    them, and also starts the change log over, so this is a guard for a client's stale band)."""
    band = held.shown.band
    return band is None or (snap.overview is not None and snap.overview.lo <= band <= snap.overview.hi)


def _agg_diff(snap: Snapshot, old: Shown, new: Shown) -> tuple[np.ndarray, np.ndarray]:
    """Aggregates entering and leaving: a diff within one band, else all of one for the other."""
    overview = snap.overview
    if overview is None or (old.band is None and new.band is None):
        return _NONE, _NONE
    if new.band is not None and old.band == new.band:
        return overview.diff(new.band, old.rect, new.rect)
    return _aggregates(snap, new.band, new.rect), _aggregates(snap, old.band, old.rect)


def _shown(snap: Snapshot, pos: int | None, show: Shown) -> bool:
    """Whether ``show`` shows the item at ``pos`` (None: not in ``snap``) itself."""
    return pos is not None and show.shows(snap.tree.get(pos))


def _agg_shown(snap: Snapshot, key: tuple[int, int], show: Shown) -> bool:
    """Whether ``show`` shows aggregate ``key`` of ``snap``."""
    band, index = key
    if band != show.band or snap.overview is None:
        return False
    try:
        return touches(snap.overview.get(band, index).box, show.rect)
    except KeyError:  # it lost its last member
        return False


def _patch(
    snap: Snapshot,
    edited: list[str],
    entered: np.ndarray,
    leaving: np.ndarray,
    agg_in: np.ndarray,
    agg_out: np.ndarray,
    new: Shown,
    held: Held,
) -> tuple[np.ndarray, np.ndarray, list[bytes]]:
    """``entered`` and ``agg_in`` plus the edited items and aggregates shown now, and the JSON
    ids of those that left: those the client was shown, or, not knowing it, all not shown and
    not leaving anyway."""
    fresh, out = set(entered.tolist()), set(leaving.tolist())
    agg_fresh, agg_gone = set(agg_in.tolist()), set(agg_out.tolist())
    more, more_aggs, gone = [], [], []
    old = held.snapshot
    for edited_id in edited:
        key = parse_agg_id(edited_id)
        if key is not None:
            if _agg_shown(snap, key, new):
                if key[1] not in agg_fresh:
                    agg_fresh.add(key[1])
                    more_aggs.append(key[1])
            elif key[0] == held.shown.band and key[1] in agg_gone:
                continue  # leaving by the band's diff already
            elif key[0] == held.shown.band and (old is None or _agg_shown(old, key, held.shown)):
                gone.append(msgspec.json.encode(edited_id))
            continue
        pos = snap.position(edited_id)
        if _shown(snap, pos, new):
            if pos not in fresh:
                fresh.add(pos)
                more.append(pos)
        elif pos in out:
            continue  # leaving by the index's diff already
        elif old is None or _shown(old, old.position(edited_id), held.shown):
            gone.append(msgspec.json.encode(edited_id))
    return (
        np.concatenate([entered, np.array(more, np.int64)]),
        np.concatenate([agg_in, np.array(more_aggs, np.int64)]),
        gone,
    )


def _tile_key(snap: Snapshot, band: int, z: int, tx: int, ty: int) -> TileKey:
    """The tile, checked: a band the document has, a level its masks can be made at."""
    overview = snap.overview
    if overview is None or overview.hi < overview.lo:
        raise NotFound("this document has no bands: it has no items to stand in for")
    if not overview.lo <= band <= overview.hi:
        raise NotFound(f"band {band}: this document's bands are {overview.lo} to {overview.hi}")
    finest, coarsest = LADDER_STEPS * band - MAX_DEPTH, LADDER_STEPS * band + MAX_HEIGHT
    if not finest <= z <= coarsest:
        raise Invalid(f"z={z}: the tiles of band {band} are of levels {finest} to {coarsest}")
    key = TileKey(band, z, tx, ty)
    if not within_reach(key):
        raise Invalid(f"tile ({tx}, {ty}) of level {z} is past the canvas's float range")
    return key


def _etags(header: str) -> set[str]:
    """The entity tags an ``If-None-Match`` lists (weak ones compare equal, as for a GET)."""
    return {tag.strip().removeprefix("W/") for tag in header.split(",") if tag.strip()}
