"""Zoomed-out answers made once: aggregates' masks kept per screen grid, and tiles.

Zoomed out, most of an answer is aggregates and their masks, and the views people share (the
whole board, the overview they zoom out to) are asked again and again. A mask is drawn in a
screen's pixel grid (``masks.Grid``: its scale, and where its pixel lines fall), so it is the
same for every screen of that grid: the same view asked by another client, or the view panned
by whole pixels. So masks are kept a *sheet* at a time, one sheet a band and grid, an
aggregate's mask made once for all the answers that show it; an answer makes only the masks its
sheet lacks, all at once. Answers stay byte for byte what they were.

Tiles are for clients that keep what they fetched: a page, a browser's cache, a CDN. Zoomed
out, the page draws at the scales of a *ladder*, ``2**(-z/4)`` pixels a unit (``z`` a whole
number), with pixel lines on the canvas's multiples of a pixel: a tile is the square of
``TILE_PIXELS`` of those pixels at ``(tx, ty)`` of one band, keyed ``(band, z, tx, ty)``: its
aggregates, and their masks together, one bitmap a kind, far smaller than a mask an aggregate.
Drawn at its own scale, a tile's bitmap falls on the screen's pixels exactly, as a mask does.

Large zoomed-out answers are kept too, gzipped once. All are made once for a document's base
and kept within a budget of bytes; an aggregate an edit changed has its mask made for each
answer, and a tile it touches is made for the version. One thread makes a given tile or answer
while the others asking for it wait, and makers take turns, as many at once as there are cores.
"""

from __future__ import annotations

import base64
import math
import os
import threading
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import orjson
import xxhash

from spatial.rect import Rect

from .looks import parse_agg_id
from .masks import MAX_ANSWER_MASK_PIXELS, MAX_MASK_PIXELS, Grid, mask_json, windows
from .responses import GZIP_LEVEL as ANSWER_GZIP_LEVEL

if TYPE_CHECKING:
    from .snapshots import Snapshot

__all__ = [
    "LADDER_STEPS",
    "MAX_DEPTH",
    "MAX_HEIGHT",
    "Prepared",
    "TILE_PIXELS",
    "Tile",
    "TileKey",
    "Tiles",
    "ladder_level",
    "ladder_scale",
    "tile_changed_since",
    "tile_keys",
    "tiles_over",
    "within_reach",
]

TILE_PIXELS = 512  # a tile's side in its pixels: a full-HD screen needs 12-20 tiles
LADDER_STEPS = 4  # ladder scales an octave: each 2**(1/4) = 1.19x the next
# A tile's pixels are at most 2**24 times finer than its band's threshold, 2**8 times coarser
MAX_DEPTH, MAX_HEIGHT = 24 * LADDER_STEPS, 8 * LADDER_STEPS
_ROOTS = tuple(2.0 ** (-k / LADDER_STEPS) for k in range(LADDER_STEPS))
_WHOLE = 2.0**50  # tile numbers past this (boxes far out, pixels fine) are not worth a tile
_GZIP_LEVEL = 6  # made once, sent many times: worth more than an answer's level
KEEP_ANSWERS_FROM = 16 << 10  # bytes: a zoomed-out screen's answer is hundreds of KB
_ENTRY_BYTES = 120
# Tiles and masks made at once in a process: as many as there are cores. More only queue for the
# interpreter's lock, and the event loop (every fast answer, /health) with them.
_MAKERS = threading.BoundedSemaphore(
    max(os.cpu_count() or 1, 1)
)  # what a kept mask costs beyond its bytes: its dict slot, its tuple


def ladder_scale(z: int) -> float:
    """Pixels a unit at ladder level ``z``: ``2**(-z/4)``, the same float wherever it is made.

    >>> ladder_scale(0), ladder_scale(4), ladder_scale(-8)
    (1.0, 0.5, 4.0)
    """
    return math.ldexp(_ROOTS[z % LADDER_STEPS], -(z // LADDER_STEPS))


def ladder_level(scale: float) -> int:
    """The ladder level nearest ``scale`` (its own, when ``scale`` is on the ladder).

    >>> ladder_level(1.0), ladder_level(0.5), ladder_level(ladder_scale(7)), ladder_level(0.55)
    (0, 4, 7, 3)
    """
    return round(-LADDER_STEPS * math.log2(scale))


class TileKey(NamedTuple):
    """A band's tile: the square of ``TILE_PIXELS`` pixels of ladder level ``z`` at ``(tx, ty)``."""

    band: int
    z: int
    tx: int
    ty: int

    @property
    def grid(self) -> Grid:
        """Its pixels: the ladder scale's, lines on the canvas's multiples of a pixel."""
        return ladder_scale(self.z), 0, 0

    @property
    def rect(self) -> Rect:
        scale = ladder_scale(self.z)
        x0, y0 = self.tx * TILE_PIXELS, self.ty * TILE_PIXELS
        return x0 / scale, y0 / scale, (x0 + TILE_PIXELS) / scale, (y0 + TILE_PIXELS) / scale


def tiles_over(band: int, z: int, rect: Rect) -> tuple[int, int, int, int]:
    """The tiles ``(tx0, ty0, tx1, ty1)``, inclusive, of ``band`` at ``z`` that ``rect`` touches."""
    scale = ladder_scale(z)
    return (
        math.floor(rect[0] * scale / TILE_PIXELS),
        math.floor(rect[1] * scale / TILE_PIXELS),
        math.floor(rect[2] * scale / TILE_PIXELS),
        math.floor(rect[3] * scale / TILE_PIXELS),
    )


def tile_keys(band: int, z: int, rect: Rect) -> Iterable[TileKey]:
    """Every tile of ``band`` at ``z`` that ``rect`` touches."""
    tx0, ty0, tx1, ty1 = tiles_over(band, z, rect)
    for ty in range(ty0, ty1 + 1):
        for tx in range(tx0, tx1 + 1):
            yield TileKey(band, z, tx, ty)


def within_reach(key: TileKey) -> bool:
    """Whether the tile is numbered within floats' reach (its corners exact, and finite)."""
    return abs(key.tx) < _WHOLE and abs(key.ty) < _WHOLE and all(map(math.isfinite, key.rect))


def tile_changed_since(snap: Snapshot, key: TileKey, version: int) -> bool:
    """Whether an edit after ``version`` (up to ``snap``) changed an aggregate touching the tile
    (True when the change log does not reach back that far). An aggregate's box never shrinks
    until the next base, so its box now holds every place an edit moved it through."""
    edited = snap.edited_since(version)
    if edited is None:
        return True
    overview = snap.overview
    assert overview is not None
    ours = [k[1] for k in map(parse_agg_id, edited) if k is not None and k[0] == key.band]
    return bool(ours) and bool(_touching(overview.boxes(key.band, np.array(ours, np.int64)), key.rect).any())


def _touching(boxes: np.ndarray, rect: Rect) -> np.ndarray:
    x0, y0, x1, y1 = rect
    return (boxes[:, 0] <= x1) & (boxes[:, 2] >= x0) & (boxes[:, 1] <= y1) & (boxes[:, 3] >= y0)


class _Mask:
    """An aggregate's mask in a grid: its window of pixels ``(c0, r0, w, h)`` (w = 0: none, too
    big), its bits, (h, w) bool, and its ``"mask"`` JSON member, made when an answer first
    needs it (a tile needs only the bits)."""

    __slots__ = ("_member", "bits", "grid", "window")

    def __init__(self, window: tuple[int, int, int, int], bits: np.ndarray, grid: Grid | None) -> None:
        self.window, self.bits, self.grid = window, bits, grid
        self._member: bytes | None = None

    @property
    def member(self) -> bytes:
        if self._member is None:
            self._member = mask_json(self.window, self.bits, self.grid) if self.grid else b""
        return self._member


_NO_MASK = _Mask((0, 0, 0, 0), np.zeros((0, 0), bool), None)


class _Sheet:
    """The masks of one band's aggregates in one grid, by index, as they were built."""

    __slots__ = ("masks", "nbytes")

    def __init__(self) -> None:
        self.masks: dict[int, _Mask] = {}
        self.nbytes = 200


def _made(snap: Snapshot, band: int, aggregates: np.ndarray, grid: Grid) -> list[_Mask]:
    """The masks of ``band``'s ``aggregates`` in ``grid``, made now, in one compiled pass."""
    return [_Mask(w, b, grid) for w, b in zip(*windows(snap, band, aggregates, grid), strict=True)]


class Tile:
    """A tile as made: its body for the tile URL, gzipped too, and its ETag."""

    __slots__ = ("body", "etag", "gzipped", "key", "nbytes")

    def __init__(self, key: TileKey, body: bytes) -> None:
        self.key, self.body = key, body
        self.gzipped = _gzip(body)
        self.etag = f'"{xxhash.xxh3_64_hexdigest(body)}"'
        self.nbytes = 300 + len(body) + len(self.gzipped)


class Prepared(bytes):
    """An answer made once for every client that asks it again: its bytes, and gzipped (on the
    first client that takes gzip: many load tools, and some proxies, never do)."""

    _gzipped: bytes | None = None

    @property
    def gzipped(self) -> bytes:
        if self._gzipped is None:  # two threads may both compress it: the same bytes
            self._gzipped = _gzip(self, ANSWER_GZIP_LEVEL)
        return self._gzipped


class Tiles:
    """A document's sheets of masks, its tiles and its large answers, the least recently used
    dropped past ``most`` bytes together. Kept from its base: a new base (an import, a
    compaction) starts them over. Thread-safe: answers run on the event loop and in threads."""

    def __init__(self, most: int = 128 << 20) -> None:
        self.most = most
        self.nbytes = 0
        self.made = self.hits = 0  # masks and tiles made, and found made
        self._base: object = None
        self._held: OrderedDict[tuple, _Sheet | Tile] = OrderedDict()
        self._answers: OrderedDict[tuple, Prepared] = OrderedDict()
        self._answer_bytes = 0
        self._lock = threading.Lock()
        self._making: dict[tuple, threading.Lock] = {}  # one maker a tile or answer: the rest wait

    def __len__(self) -> int:
        return len(self._held)

    def stats(self) -> dict[str, int]:
        return {"held": len(self._held), "bytes": self.nbytes, "made": self.made, "hits": self.hits}

    def masks(self, snap: Snapshot, band: int, aggregates: np.ndarray, grid: Grid) -> list[bytes]:
        """The ``"mask"`` JSON member of each of ``band``'s ``aggregates`` in ``grid``, in order
        (``b""`` for one without: too big, or past the answer's MAX_ANSWER_MASK_PIXELS, as
        ``masks.masks`` answers): kept, or made now (those an edit changed, every time)."""
        return [m.member for m in self._masks(snap, band, aggregates, grid)]

    def _masks(self, snap: Snapshot, band: int, aggregates: np.ndarray, grid: Grid) -> list[_Mask]:
        """``masks``, with their windows and bits."""
        overview = snap.overview
        assert overview is not None
        indices = aggregates.tolist()
        edited = overview.edited(band, aggregates).tolist() if snap.edits else [False] * len(indices)
        with self._lock:
            kept = self._sheet((band, grid), snap).masks
            found = [None if e else kept.get(i) for i, e in zip(indices, edited, strict=True)]
        missing = [at for at, mask in enumerate(found) if mask is None]
        if missing:
            with _MAKERS:
                made = _made(snap, band, aggregates[missing], grid)
            # A mask made without one was too big, unless the answer's total cut it: it cannot
            # have while the masks made hold less than the total less the largest mask.
            sure = sum(m.window[2] * m.window[3] for m in made) <= MAX_ANSWER_MASK_PIXELS - MAX_MASK_PIXELS
            with self._lock:
                sheet = self._sheet((band, grid), snap)
                for at, mask in zip(missing, made, strict=True):
                    found[at] = mask
                    if not edited[at] and (mask.window[2] or sure) and indices[at] not in sheet.masks:
                        sheet.masks[indices[at]] = mask
                        cost = mask.bits.nbytes * 3 // 2 + _ENTRY_BYTES  # and its JSON, once made
                        sheet.nbytes += cost
                        self.nbytes += cost
                self.made += len(missing)
                self._keep_to_budget()
        with self._lock:
            self.hits += len(indices) - len(missing)
        out, total = [], 0  # in order, while the windows fit in the answer's total together
        for one in found:
            assert one is not None  # every one missing was made
            total += one.window[2] * one.window[3]
            out.append(one if total <= MAX_ANSWER_MASK_PIXELS else _NO_MASK)
        return out

    def answer(self, snap: Snapshot, key: tuple, make: Callable[[], bytes], small: bool = False) -> bytes:
        """The answer to the request ``key`` names at ``snap``'s version: kept, or ``make()``
        now, kept when it is large (``Prepared``). Zoomed out, a view people share (the whole
        board) is asked again and again: the same bytes, gzipped once. Answers have half of the
        budget to themselves, so those seldom asked twice never push the masks out; a
        small one (a pan's) is not worth a lookup, let alone a compression, unless ``small``
        (a tiled answer: small, but choosing its band took the work)."""
        held = (snap.version, *key)
        found = self._answer(snap, held)
        if found is not None:
            return found
        with self._one_maker(("answer", held)):  # a hundred clients opening the board at once
            found = self._answer(snap, held)
            if found is not None:
                return found
            made = make()
            if len(made) < KEEP_ANSWERS_FROM and not small:
                return made
            return self._keep_answer(snap, held, Prepared(made))

    def _answer(self, snap: Snapshot, held: tuple) -> Prepared | None:
        with self._lock:
            self._check_base(snap)
            found = self._answers.get(held)
            if found is not None:
                self._answers.move_to_end(held)
                self.hits += 1
            return found

    def _keep_answer(self, snap: Snapshot, held: tuple, body: Prepared) -> Prepared:
        with self._lock:
            if self._base is snap.table and held not in self._answers:
                self._answers[held] = body
                self._answer_bytes += _answer_bytes(body)
                self.nbytes += _answer_bytes(body)
                while self._answer_bytes > self.most // 2:
                    dropped = _answer_bytes(self._answers.popitem(last=False)[1])
                    self._answer_bytes -= dropped
                    self.nbytes -= dropped
        return body

    def tile(self, snap: Snapshot, key: TileKey) -> Tile:
        """``key``'s tile as ``snap`` shows it: kept, or made now (milliseconds)."""
        held = self._held_as(snap, key)
        tile = self._kept(snap, held)
        if tile is not None:
            return tile
        with self._one_maker(("tile", held)):  # every client of a board at Fit asks the same
            tile = self._kept(snap, held)
            if tile is not None:
                return tile
            overview = snap.overview
            assert overview is not None
            aggregates = overview.query(key.band, key.rect)
            masks = self._masks(snap, key.band, aggregates, key.grid)
            with _MAKERS:
                tile = Tile(key, _body(snap, key, aggregates, masks))
            with self._lock:
                if self._base is snap.table and held not in self._held:
                    self._held[held] = tile
                    self.nbytes += tile.nbytes
                    self.made += 1
                    self._keep_to_budget()
            return tile

    @contextmanager
    def _one_maker(self, what: tuple) -> Iterator[None]:
        """Held while ``what`` is made: who asks for it meanwhile waits, then finds it made."""
        with self._lock:
            gate = self._making.setdefault(what, threading.Lock())
        try:
            with gate:
                yield
        finally:
            with self._lock:
                if self._making.get(what) is gate:
                    del self._making[what]

    def kept(self, snap: Snapshot, key: TileKey) -> Tile | None:
        """``key``'s tile as ``snap`` shows it, if it is made already."""
        return self._kept(snap, self._held_as(snap, key))

    def _kept(self, snap: Snapshot, held: tuple) -> Tile | None:
        with self._lock:
            self._check_base(snap)
            tile = self._held.get(held)
            if not isinstance(tile, Tile):
                return None
            self._held.move_to_end(held)
            self.hits += 1
            return tile

    @staticmethod
    def _held_as(snap: Snapshot, key: TileKey) -> tuple:
        """What a tile is kept as: its key, and the version it was made for when an edit since
        the base changed an aggregate touching it (None: the base's serves every version)."""
        if not snap.edits:
            return key, None
        overview = snap.overview
        assert overview is not None
        aggregates = overview.query(key.band, key.rect)
        return key, snap.version if overview.edited(key.band, aggregates).any() else None

    def _sheet(self, key: tuple, snap: Snapshot) -> _Sheet:
        """The sheet at ``key`` (under the lock), a new one if need be, as the most recently used."""
        self._check_base(snap)
        sheet = self._held.get(key)
        if not isinstance(sheet, _Sheet):
            sheet = self._held[key] = _Sheet()
            self.nbytes += sheet.nbytes
        self._held.move_to_end(key)
        return sheet

    def _check_base(self, snap: Snapshot) -> None:
        if self._base is not snap.table:  # a new base renumbers every aggregate
            self._base, self._held, self._answers = snap.table, OrderedDict(), OrderedDict()
            self.nbytes = self._answer_bytes = 0

    def _keep_to_budget(self) -> None:
        while self.nbytes > self.most and len(self._held) > 1:
            self.nbytes -= self._held.popitem(last=False)[1].nbytes


def _answer_bytes(body: Prepared) -> int:
    return 200 + 3 * len(body) // 2  # its gzipped bytes too, once asked: a third of it at most


def _body(snap: Snapshot, key: TileKey, aggregates: np.ndarray, masks: list[_Mask]) -> bytes:
    """The tile URL's JSON: where the tile is; the band's aggregates touching it, as columns
    (``index``: the id is ``~band.index``; ``box`` in the tile's pixels from its corner, rounded
    outward, four a box; ``cover`` in thousandths; ``boxed``: positions of those drawn as their
    box, having no mask); and each kind's pixels their members touch, ``size`` rows of ``size``
    bits, least significant first, deflated (zlib) and base64."""
    overview, looks = snap.overview, snap.looks
    assert overview is not None and looks is not None
    scale = ladder_scale(key.z)
    c0, r0 = key.tx * TILE_PIXELS, key.ty * TILE_PIXELS
    boxes, count, cover, kind, z = overview.rows(key.band, aggregates)
    with np.errstate(over="ignore", invalid="ignore"):
        pixels = np.concatenate(
            [np.floor(boxes[:, :2] * scale) - (c0, r0), np.ceil(boxes[:, 2:] * scale) - (c0, r0)], axis=1
        )
    pixels = np.clip(np.nan_to_num(pixels), -(2**40), 2**40).astype(np.int64)
    layers: dict[str, np.ndarray] = {}
    boxed = []
    for at, (mask, k) in enumerate(zip(masks, kind.tolist(), strict=True)):
        if not mask.window[2]:
            boxed.append(at)
            continue
        name = looks.names[k]
        layer = layers.get(name)
        if layer is None:
            layer = layers[name] = np.zeros((TILE_PIXELS, TILE_PIXELS), bool)
        _paint(layer, mask, c0, r0)
    return orjson.dumps(
        {
            "band": key.band,
            "z": key.z,
            "tx": key.tx,
            "ty": key.ty,
            "scale": scale,
            "box": key.rect,
            "size": TILE_PIXELS,
            "aggregates": {
                "index": aggregates,
                "box": pixels.ravel(),
                "count": count.astype(np.int64),
                "cover": np.rint(np.clip(cover, 0, 1) * 1000).astype(np.int64),
                "kind": [looks.names[k] for k in kind.tolist()],
                "z": z.astype(np.int64),
                "boxed": boxed,
            },
            "layers": {
                name: base64.b64encode(
                    zlib.compress(np.packbits(layer, bitorder="little").tobytes(), 6)
                ).decode()
                for name, layer in sorted(layers.items())
            },
        },
        option=orjson.OPT_SERIALIZE_NUMPY,
    )


def _paint(layer: np.ndarray, mask: _Mask, c0: int, r0: int) -> None:
    """OR ``mask``'s bits into ``layer``, the tile whose pixel (0, 0) is the grid's ``(c0, r0)``,
    clipped to it."""
    mc, mr, w, h = mask.window
    mc, mr = mc - c0, mr - r0
    x0, y0, x1, y1 = max(mc, 0), max(mr, 0), min(mc + w, TILE_PIXELS), min(mr + h, TILE_PIXELS)
    if x0 < x1 and y0 < y1:
        layer[y0:y1, x0:x1] |= mask.bits[y0 - mr : y1 - mr, x0 - mc : x1 - mc]


def _gzip(body: bytes, level: int = _GZIP_LEVEL) -> bytes:
    """``body`` as a gzip member (what ``Content-Encoding: gzip`` sends)."""
    packer = zlib.compressobj(level, zlib.DEFLATED, 31)
    return packer.compress(body) + packer.flush()
