"""Tiles: zoomed-out answers made once, in squares fixed in canvas space.

Zoomed out, most of an answer is aggregates and their masks, and the views people share (the
whole board, the overview they zoom out to) are asked again and again, each for a slightly
different screen. So the masks are not drawn in each screen's pixels: they are drawn in a grid
fixed in the canvas, of cells ``2**z`` units (``z`` from the screen's scale, ``FINER`` levels
under its pixel), and a band's aggregates are made a *tile* at a time: the square of
``TILE_CELLS`` cells at ``(tx, ty)``, keyed ``(band, z, tx, ty)``. A tile is made once for a
document's base and kept (every answer, every client); an edit remakes only the tiles whose
aggregates it changed.

A tile serves twice. Answers (``/viewport``, ``/diff``, the stream) take each aggregate's JSON,
its mask included, from the tile its box starts in. The tile URL (``routers.tiles``) sends the
tile whole for a browser or a CDN to keep: its aggregates without masks, and their masks
together, one bitmap a kind (deflated, base64), far smaller than a mask an aggregate.

A cell is drawn as every screen pixel it touches (as a mask's pixels were), so a mask drawn at
a scale between two levels covers at most a fraction of a pixel more than its members: the
trade ``benchmarks.tradeoffs --trades aggregates`` measures.
"""

from __future__ import annotations

import base64
import math
import threading
import zlib
from collections import OrderedDict
from collections.abc import Iterable
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import orjson
import xxhash

from spatial.rect import Rect

from .looks import agg_json, parse_agg_id
from .masks import MAX_ANSWER_MASK_PIXELS, MAX_MASK_PIXELS, PHASE_STEPS

if TYPE_CHECKING:
    from .snapshots import Snapshot

__all__ = [
    "FINER",
    "MAX_DEPTH",
    "TILE_CELLS",
    "Tile",
    "TileKey",
    "Tiles",
    "level",
    "tile_changed_since",
    "tile_keys",
    "tiles_over",
    "within_reach",
]

TILE_CELLS = 512  # cells along a tile's side: a full-HD screen needs 12-20 tiles
# Mask cells under a screen pixel: 0, a cell is 1/2..1 pixel; 1, 1/4..1/2. Finer cells stray
# less past the members they stand for, at more bytes (see docs/TRADEOFFS.md).
FINER = 1
MAX_DEPTH = 24  # a tile's cells are at most this many levels under its band's threshold
_WHOLE = 2.0**50  # tile numbers past this (boxes far out, cells fine) are not worth a tile
_GZIP_LEVEL = 6  # made once, sent many times: worth more than an answer's level


def level(scale: float) -> int:
    """The level of a screen of ``scale`` pixels a unit: its cells are ``2**level`` units, the
    largest power of two ``FINER`` halvings under a pixel.

    >>> [level(s) for s in (1.0, 0.75, 0.5, 4.0)] == [-FINER, -FINER, 1 - FINER, -2 - FINER]
    True
    """
    _, exponent = math.frexp(1.0 / scale)  # a pixel is mantissa * 2**exponent units
    return exponent - 1 - FINER


class TileKey(NamedTuple):
    """A band's tile: the square of ``TILE_CELLS`` cells of ``2**z`` units at ``(tx, ty)``."""

    band: int
    z: int
    tx: int
    ty: int

    @property
    def side(self) -> float:
        return math.ldexp(TILE_CELLS, self.z)

    @property
    def rect(self) -> Rect:
        side = self.side
        return self.tx * side, self.ty * side, (self.tx + 1) * side, (self.ty + 1) * side


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
    ours = [key_[1] for key_ in map(parse_agg_id, edited) if key_ is not None and key_[0] == key.band]
    if not ours:
        return False
    boxes = overview.boxes(key.band, np.array(ours, np.int64))
    x0, y0, x1, y1 = key.rect
    return bool(((boxes[:, 0] <= x1) & (boxes[:, 2] >= x0) & (boxes[:, 1] <= y1) & (boxes[:, 3] >= y0)).any())


def tiles_over(band: int, z: int, rect: Rect) -> tuple[int, int, int, int]:
    """The tiles ``(tx0, ty0, tx1, ty1)``, inclusive, of ``band`` at ``z`` that ``rect`` touches."""
    side = math.ldexp(TILE_CELLS, z)
    return (
        math.floor(rect[0] / side),
        math.floor(rect[1] / side),
        math.floor(rect[2] / side),
        math.floor(rect[3] / side),
    )


class Tile:
    """A tile as made: the band's aggregates touching it (sorted), their kinds, and their JSON
    with their masks. Its body for the tile URL is made on the first ask (``served``), deflated
    too, with its ETag: answers never need it."""

    __slots__ = ("_by_index", "_served", "aggregates", "entries", "key", "kinds", "nbytes")

    def __init__(self, key: TileKey, aggregates: np.ndarray, entries: list[bytes], kinds: np.ndarray) -> None:
        self.key, self.aggregates, self.entries, self.kinds = key, aggregates, entries, kinds
        self._served: tuple[bytes, bytes, str] | None = None
        self._by_index = dict(zip(aggregates.tolist(), entries, strict=True))
        self.nbytes = 200 + aggregates.nbytes + sum(len(e) + 120 for e in entries)

    def entry(self, index: int) -> bytes | None:
        """Aggregate ``index``'s JSON with its mask; None when it does not touch the tile."""
        return self._by_index.get(index)

    def layers(self, names: tuple[str, ...]) -> dict[str, np.ndarray]:
        """Each kind's cells of the tile its aggregates' members touch, (TILE_CELLS, TILE_CELLS):
        the masks painted together, read back from the entries."""
        x0, y0, _, _ = self.key.rect
        cell = math.ldexp(1.0, self.key.z)
        layers: dict[str, np.ndarray] = {}
        for entry, kind in zip(self.entries, self.kinds.tolist(), strict=True):
            at = entry.find(b',"mask":')
            if at < 0:
                continue
            mask = orjson.loads(entry[at + 8 : -1])
            w, h = mask["w"], mask["h"]
            bits = np.unpackbits(
                np.frombuffer(base64.b64decode(mask["bits"]), np.uint8), count=w * h, bitorder="little"
            )
            window = (round((mask["x0"] - x0) / cell), round((mask["y0"] - y0) / cell), w, h)
            name = names[kind]
            layer = layers.get(name)
            if layer is None:
                layer = layers[name] = np.zeros((TILE_CELLS, TILE_CELLS), bool)
            _paint(layer, window, bits.reshape(h, w).astype(bool))
        return layers

    def served(self, snap: Snapshot) -> tuple[bytes, bytes, str]:
        """``(body, gzipped body, ETag)`` for the tile URL (made once; ``snap``: the one it was
        made from, or one sharing its aggregates)."""
        if self._served is None:
            body = _body(snap, self)
            self._served = body, zlib_gzip(body), f'"{xxhash.xxh3_64_hexdigest(body)}"'
            self.nbytes += len(body) + len(self._served[1])
        return self._served


def make(snap: Snapshot, keys: list[TileKey]) -> list[Tile]:
    """``keys``' tiles of ``snap`` (which has an overview), all of one band and level, together:
    the masks of the band's aggregates touching any of them in one compiled pass (a mask is the
    same whichever tile it is made for: the cells are on one grid)."""
    overview, looks = snap.overview, snap.looks
    assert overview is not None and looks is not None
    band, z = keys[0].band, keys[0].z
    cell = math.ldexp(1.0, z)
    rects = np.array([k.rect for k in keys])
    region = (*rects[:, :2].min(0).tolist(), *rects[:, 2:].max(0).tolist())
    aggs = overview.query(band, region)
    boxes, _, _, kind, _ = overview.rows(band, aggs)
    windows, bits = overview.masks(
        band,
        aggs,
        (region[0], region[1]),
        1.0 / cell,
        snap.tree,
        snap.item_boxes,
        MAX_MASK_PIXELS,
        1 / PHASE_STEPS,
        MAX_ANSWER_MASK_PIXELS,
    )
    bodies = agg_json(overview, looks.names, band, aggs)
    members = []  # each aggregate's "mask" member: b"" without one (too big: drawn as its box)
    for (c0, r0, w, h), mask in zip(windows, bits, strict=True):
        if not w:
            members.append(b"")
            continue
        x0, y0 = float(region[0] + c0 * cell), float(region[1] + r0 * cell)
        packed = base64.b64encode(np.packbits(mask, bitorder="little").tobytes()).decode()
        members.append(
            f',"mask":{{"x0":{x0!r},"y0":{y0!r},"cell":{cell!r},"w":{w},"h":{h},"bits":"{packed}"}}}}'.encode()
        )
    order = np.argsort(aggs, kind="stable")
    tiles = []
    for key, (x0, y0, x1, y1) in zip(keys, rects.tolist(), strict=True):
        at = order[
            (boxes[order, 0] <= x1)
            & (boxes[order, 2] >= x0)
            & (boxes[order, 1] <= y1)
            & (boxes[order, 3] >= y0)
        ]
        entries = [bodies[i][:-1] + members[i] if members[i] else bodies[i] for i in at.tolist()]
        tiles.append(Tile(key, aggs[at], entries, kind[at]))
    return tiles


def _paint(layer: np.ndarray, window: tuple[int, int, int, int], mask: np.ndarray) -> None:
    """OR ``mask`` (at ``window``, in the tile's cells) into ``layer``, clipped to the tile."""
    c0, r0, w, h = window
    x0, y0, x1, y1 = max(c0, 0), max(r0, 0), min(c0 + w, TILE_CELLS), min(r0 + h, TILE_CELLS)
    if x0 < x1 and y0 < y1:
        layer[y0:y1, x0:x1] |= mask[y0 - r0 : y1 - r0, x0 - c0 : x1 - c0]


def _body(snap: Snapshot, tile: Tile) -> bytes:
    """The tile URL's JSON: where the tile is; its aggregates as columns (``index``: the id is
    ``~band.index``; ``box`` in the tile's cells, rounded outward, four a box; ``cover`` in
    thousandths; ``boxed``: drawn as its box, having no mask); and each kind's cells their
    members touch, ``size`` rows of ``size`` bits, least significant first, deflated (zlib)
    and base64."""
    overview, looks = snap.overview, snap.looks
    assert overview is not None and looks is not None
    key = tile.key
    x0, y0, _, _ = key.rect
    cell = math.ldexp(1.0, key.z)
    boxes, count, cover, kind, z = overview.rows(key.band, tile.aggregates)
    with np.errstate(over="ignore", invalid="ignore"):
        cells = np.concatenate(
            [np.floor((boxes[:, :2] - (x0, y0)) / cell), np.ceil((boxes[:, 2:] - (x0, y0)) / cell)], axis=1
        )
    cells = np.clip(np.nan_to_num(cells), -(2**40), 2**40).astype(np.int64)
    boxed = [i for i, e in enumerate(tile.entries) if b'"mask":' not in e]
    return orjson.dumps(
        {
            "band": key.band,
            "z": key.z,
            "tx": key.tx,
            "ty": key.ty,
            "box": key.rect,
            "cell": cell,
            "size": TILE_CELLS,
            "aggregates": {
                "index": tile.aggregates,
                "box": cells.ravel(),
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
                for name, layer in sorted(tile.layers(looks.names).items())
            },
        },
        option=orjson.OPT_SERIALIZE_NUMPY,
    )


def zlib_gzip(body: bytes) -> bytes:
    """``body`` as a gzip member (what ``Content-Encoding: gzip`` sends)."""
    packer = zlib.compressobj(_GZIP_LEVEL, zlib.DEFLATED, 31)
    return packer.compress(body) + packer.flush()


class Tiles:
    """A document's tiles, the least recently used dropped past ``most`` bytes. Tiles made
    from its base serve every version while no edit changes their aggregates; a tile an edit
    touched is made for the version that asks and kept beside them. Thread-safe: answers run
    on the event loop and in the thread pool."""

    def __init__(self, most: int = 64 << 20) -> None:
        self.most = most
        self.nbytes = 0
        self.made = self.hits = 0
        self._base: object = None
        self._held: OrderedDict[tuple, Tile] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._held)

    def get(self, snap: Snapshot, key: TileKey) -> Tile:
        """``key``'s tile as ``snap`` shows it: kept, or made now."""
        return self.get_all(snap, [key])[0]

    def get_all(self, snap: Snapshot, keys: list[TileKey]) -> list[Tile]:
        """The tiles at ``keys`` (of one band and level) as ``snap`` shows them: those kept, and
        the others made now, together."""
        held = [(key, self._edited_version(snap, key)) for key in keys]
        out: list[Tile | None] = []
        with self._lock:
            if self._base is not snap.table:  # a new base renumbers every aggregate
                self._base, self._held, self.nbytes = snap.table, OrderedDict(), 0
            for at in held:
                tile = self._held.get(at)
                if tile is not None:
                    self._held.move_to_end(at)
                    self.hits += 1
                out.append(tile)
        missing = [i for i, tile in enumerate(out) if tile is None]
        if missing:  # made outside the lock: two makers of one tile make the same bytes
            made = make(snap, [keys[i] for i in missing])
            with self._lock:
                for i, tile in zip(missing, made, strict=True):
                    out[i] = tile
                    if self._base is snap.table and held[i] not in self._held:
                        self._held[held[i]] = tile
                        self.nbytes += tile.nbytes
                        self.made += 1
                self._keep_to_budget()
        return out  # type: ignore[return-value]  # every None was replaced

    def counted(self, tile: Tile, before: int) -> None:
        """``tile`` grew from ``before`` bytes (its body was made): count it."""
        with self._lock:
            self.nbytes += tile.nbytes - before
            self._keep_to_budget()

    def _keep_to_budget(self) -> None:
        while self.nbytes > self.most and len(self._held) > 1:
            self.nbytes -= self._held.popitem(last=False)[1].nbytes

    def entries(self, snap: Snapshot, band: int, z: int, aggregates: np.ndarray) -> list[bytes]:
        """The JSON of ``band``'s ``aggregates`` with their masks at level ``z``, in order, each
        from the tile its box starts in.

        :raises OverflowError: when boxes are too far out for tiles of ``z`` to number
        """
        overview = snap.overview
        assert overview is not None
        boxes = overview.boxes(band, aggregates)
        side = math.ldexp(TILE_CELLS, z)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            cols, rows = np.floor(boxes[:, 0] / side), np.floor(boxes[:, 1] / side)
        if not (np.abs(cols) < _WHOLE).all() or not (np.abs(rows) < _WHOLE).all():
            raise OverflowError(f"tiles of {side!r} units do not number boxes this far out")
        homes = np.unique(np.stack([cols, rows], axis=1), axis=0).astype(np.int64).tolist()
        tiles = dict(
            zip(
                map(tuple, homes),
                self.get_all(snap, [TileKey(band, z, tx, ty) for tx, ty in homes]),
                strict=True,
            )
        )
        out: list[bytes] = []
        for index, tx, ty in zip(
            aggregates.tolist(), cols.astype(np.int64).tolist(), rows.astype(np.int64).tolist(), strict=True
        ):
            entry = tiles[tx, ty].entry(index)
            if entry is None:  # a quotient rounded up names the tile after its corner's
                entry = next(
                    (
                        e
                        for at in ((tx - 1, ty), (tx, ty - 1), (tx - 1, ty - 1))
                        if (e := self._near(snap, band, z, at, index)) is not None
                    ),
                    None,
                )
                if entry is None:
                    raise KeyError(f"aggregate {index} of band {band} is in no tile around its corner")
            out.append(entry)
        return out

    def _near(self, snap: Snapshot, band: int, z: int, at: tuple[int, int], index: int) -> bytes | None:
        return self.get(snap, TileKey(band, z, *at)).entry(index)

    def _edited_version(self, snap: Snapshot, key: TileKey) -> int | None:
        """None when no edit since the base changed an aggregate touching ``key``'s tile (its
        base tile serves), else ``snap``'s version (the tile is made for it)."""
        overview = snap.overview
        if overview is None or not snap.edits:
            return None
        touching = overview.query(key.band, key.rect)
        return snap.version if len(touching) and overview.edited(key.band, touching).any() else None

    def stats(self) -> dict[str, int]:
        return {"tiles": len(self._held), "bytes": self.nbytes, "made": self.made, "hits": self.hits}


def tile_keys(band: int, z: int, rect: Rect) -> Iterable[TileKey]:
    """Every tile of ``band`` at ``z`` that ``rect`` touches."""
    tx0, ty0, tx1, ty1 = tiles_over(band, z, rect)
    for ty in range(ty0, ty1 + 1):
        for tx in range(tx0, tx1 + 1):
            yield TileKey(band, z, tx, ty)
