"""How items look, for the overview: each item's kind (as a code) and z, and the JSON of the
aggregates that stand in for items too small to draw.

An aggregate goes to clients in an item's shape, with an ``agg`` object that real items never
have, and an id no item can have (item ids may not start with ``~``)::

    {"id": "~6.1207", "x0": 72.0, "y0": 88.0, "x1": 540.0, "y1": 760.0, "kind": "text", "z": 3,
     "agg": {"count": 412, "cover": 0.37}}
"""

from __future__ import annotations

import itertools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import msgspec
import numba
import numpy as np
import orjson

from spatial.kernels import copy
from spatial.overview import Overview
from spatial.paging import Scratch, in_steps, new_array, release_rows

from .table import Packed, fnv1a

__all__ = ["AGG_PREFIX", "Looks", "agg_id", "agg_json", "band_json", "parse_agg_id"]

AGG_PREFIX = "~"


class _Look(msgspec.Struct):
    kind: str = "box"
    z: int = 0


_look = msgspec.json.Decoder(_Look)


@dataclass(frozen=True)
class Looks:
    """The kinds items have, by code: an aggregate's kind is a code into ``names``."""

    names: tuple[str, ...]
    codes: dict[str, int] = field(default_factory=dict)

    @classmethod
    def of(cls, bodies: Packed, scratch: Scratch | None = None) -> tuple[Looks, np.ndarray, np.ndarray]:
        """The looks of the items whose response JSON is ``bodies``, and each item's kind code
        and z, ``(looks, kinds, z)``. Cost: one compiled pass over the bytes, two steps at a
        time on two cores; a body whose kind the pass cannot read plainly (an escape in it) is
        decoded. It holds the two columns it returns (4 bytes an item each) and a step's
        scan: each step's kinds are coded as it is scanned (``_Kinds``). With ``scratch``, the
        columns are made in its files, each step's pages handed back once written: it holds a
        step's scan (an import's: 800 MB less at 1e8 items)."""
        n = len(bodies)
        kinds, z = new_array(scratch, n, np.int32), new_array(scratch, n, np.int32)
        coded = _Kinds(kinds)
        with ThreadPoolExecutor(2) as pool:
            steps = bodies.steps()  # a spilled buffer's pages handed back as the next is asked for
            for step in steps:
                both = [step, *itertools.islice(steps, 1)]
                scans = pool.map(lambda s: _scan(bodies.array, bodies.offsets[s[0] : s[1] + 1]), both)
                for (lo, hi), (hashes, zs, plain) in zip(both, scans, strict=True):
                    for i in np.flatnonzero(~plain).tolist():  # escapes in the kind: decode those bodies
                        look = _look.decode(bodies[lo + i])
                        key = msgspec.json.encode(look.kind)[1:-1]
                        hashes[i] = fnv1a(np.frombuffer(key, np.uint8), np.array([0, len(key)], np.int64))[0]
                        zs[i] = look.z
                    z[lo:hi] = zs
                    coded.step(hashes, lo)
                    for column in (z, kinds):
                        release_rows(column[lo:hi])
        first = coded.ranked()
        names = [_look.decode(bodies[int(i)]).kind for i in first.tolist()]
        if len(set(names)) != len(names):  # two kinds with one hash: name them the slow way
            codes: dict[str, int] = {}
            kinds = np.array(
                [codes.setdefault(_look.decode(bodies[i]).kind, len(codes)) for i in range(n)], np.int32
            )
            names = list(codes)
        # int32, as the overview takes them: 8 bytes an item less through its build's peak
        return cls(tuple(names), {n: k for k, n in enumerate(names)}), _held(kinds), _held(z)

    def of_body(self, body: bytes) -> tuple[int, int]:
        """``(kind code, z)`` of one item's JSON (its kind known: see ``with_item``)."""
        look = _look.decode(body)
        return self.codes[look.kind], look.z

    def with_item(self, body: bytes) -> Looks:
        """These looks, knowing the kind of the item ``body`` too."""
        kind = _look.decode(body).kind
        if kind in self.codes:
            return self
        return Looks((*self.names, kind), {**self.codes, kind: len(self.names)})


def _held(column: np.ndarray) -> np.ndarray:
    """``column``, or one value seen ``len(column)`` times when it holds one only (a document
    of one kind, or all at z 0): the overview's build holds it through its peak, 4 bytes an
    item (400 MB at 1e8 items) for nothing. Read a step at a time (mapped: handed back)."""
    if not len(column) or any((step != column[0]).any() for _, step in in_steps(column)):
        return column
    return np.broadcast_to(column[:1].copy(), column.shape)


class _Kinds:
    """Items' kind codes, into ``codes``, from their kinds' hashes a step at a time: each kind
    numbered as first seen while there are at most ``_FEW`` (a document has a few), noting
    where it first is; ``ranked`` then renumbers them in hash order, as ``np.unique`` of every
    hash would. Past ``_FEW`` kinds every hash is kept (8 bytes an item) and sorted at the end."""

    def __init__(self, codes: np.ndarray) -> None:
        self.codes = codes
        self.found: dict[int, tuple[int, int]] = {}  # hash -> (code, first item)
        self.hashes: np.ndarray | None = None  # every item's hash, once there are many kinds

    def step(self, hashes: np.ndarray, lo: int) -> None:
        """Code items ``lo..`` whose kinds' hashes these are."""
        hi = lo + len(hashes)
        if self.hashes is None:
            distinct, first, codes = _first_seen(hashes, _FEW)
            if codes is not None:
                for h, f in zip(distinct.tolist(), first.tolist(), strict=True):
                    self.found.setdefault(h, (len(self.found), lo + f))
                if len(self.found) <= _FEW:
                    self.codes[lo:hi] = np.array([self.found[h][0] for h in distinct.tolist()])[codes]
                    return
            # Many kinds: every hash kept from here, the steps before's from their codes
            self.hashes = np.empty(len(self.codes), np.uint64)
            self.hashes[:lo] = np.array(list(self.found), np.uint64)[self.codes[:lo]]
        self.hashes[lo:hi] = hashes

    def ranked(self) -> np.ndarray:
        """The codes renumbered in place in hash order; where each kind first is, in that order."""
        if self.hashes is not None:
            _, first, ranks = np.unique(self.hashes, return_index=True, return_inverse=True)
            self.codes[:] = ranks
            return first
        found = np.array(list(self.found), np.uint64)
        order = np.argsort(found)
        rank = np.empty(len(order), np.int32)
        rank[order] = np.arange(len(order), dtype=np.int32)
        for _, step in in_steps(self.codes):  # a step at a time: no copy of them all
            step[:] = rank[step]
        return np.array([first for _, first in self.found.values()], np.int64)[order]


_FEW = 4096


@numba.njit(cache=True, nogil=True)
def _first_seen(hashes: np.ndarray, most: int):  # pragma: no cover - compiled
    """The distinct hashes in the order first seen, where each is first, and each item's index
    among them; codes None past ``most`` distinct."""
    size = 1
    while size < 2 * most:
        size *= 2
    slots = np.full(size, -1, np.int64)  # index into found, by hash
    found = np.empty(most, np.uint64)
    first = np.empty(most, np.int64)
    codes = np.empty(len(hashes), np.int64)
    count = 0
    for i in range(len(hashes)):
        h = hashes[i]
        slot = np.int64(h & np.uint64(size - 1))
        while slots[slot] >= 0 and found[slots[slot]] != h:
            slot = (slot + 1) & (size - 1)
        if slots[slot] < 0:
            if count == most:
                return found[:0], first[:0], None
            slots[slot], found[count], first[count] = count, h, i
            count += 1
        codes[i] = slots[slot]
    return found[:count], first[:count], codes


_KIND = np.frombuffer(b',"kind":"', np.uint8)
_Z = np.frombuffer(b',"z":', np.uint8)


@numba.njit(cache=True, nogil=True)
def _scan(
    buffer: np.ndarray, offsets: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Per body: the FNV-1a hash of its kind's bytes, its z, and whether both read plainly.

    Bodies are msgspec's encoding of an item, fields in order, so the kind follows the box as
    ``,"kind":"...","z":N``; that byte sequence cannot occur inside a JSON string (its quotes
    would be escaped), so its first occurrence is the field.
    """
    n = len(offsets) - 1
    hashes = np.zeros(n, np.uint64)
    z = np.zeros(n, np.int64)
    plain = np.zeros(n, np.bool_)
    for i in range(n):
        j, end = offsets[i], offsets[i + 1]
        found = False
        while j + len(_KIND) <= end:
            k = 0
            while k < len(_KIND) and buffer[j + k] == _KIND[k]:
                k += 1
            if k == len(_KIND):
                found = True
                break
            j += 1
        if not found:
            continue
        j += len(_KIND)
        h = np.uint64(14695981039346656037)
        escaped = False
        while j < end and buffer[j] != 34:  # the closing quote
            escaped = escaped or buffer[j] == 92  # a backslash
            h = (h ^ np.uint64(buffer[j])) * np.uint64(1099511628211)
            j += 1
        j += 1
        if escaped or j + len(_Z) > end:
            continue
        k = 0
        while k < len(_Z) and buffer[j + k] == _Z[k]:
            k += 1
        if k < len(_Z):
            continue
        j += len(_Z)
        sign, value, digits = 1, 0, 0
        if j < end and buffer[j] == 45:  # "-"
            sign, j = -1, j + 1
        while j < end and 48 <= buffer[j] <= 57:
            value = value * 10 + (buffer[j] - 48)
            digits += 1
            j += 1
        if digits:
            hashes[i], z[i], plain[i] = h, sign * value, True
    return hashes, z, plain


def agg_id(key: tuple[int, int]) -> str:
    """The id of aggregate ``index`` of ``band``: ``~band.index``."""
    band, index = key
    return f"{AGG_PREFIX}{band}.{index}"


def parse_agg_id(text: str) -> tuple[int, int] | None:
    """``(band, index)`` of an aggregate id, or None for an item id."""
    if not text.startswith(AGG_PREFIX):
        return None
    band, _, index = text[1:].partition(".")
    return int(band), int(index)


def agg_json(overview: Overview, names: tuple[str, ...], band: int, indices: np.ndarray) -> list[bytes]:
    """The JSON of ``band``'s aggregates at ``indices``, one by one (for the few edits changed)."""
    packed = _encode(band, indices, *overview.rows(band, indices), names)
    return [bytes(packed[i]) for i in range(len(packed))]  # bytes already: the same objects


def band_json(overview: Overview, names: tuple[str, ...], band: int) -> Packed:
    """The JSON of every aggregate ``band`` was built with, as built (edits change some: see
    ``Overview.edited``), packed. Cost: compiled, ~0.1 us an aggregate."""
    indices = np.arange(overview.built(band))
    return _encode(band, indices, *overview.rows(band, indices, as_built=True), names)


def _encode(
    band: int,
    indices: np.ndarray,
    boxes: np.ndarray,
    count: np.ndarray,
    cover: np.ndarray,
    kind: np.ndarray,
    z: np.ndarray,
    names: tuple[str, ...],
) -> Packed:
    numbers = orjson.dumps(np.ascontiguousarray(boxes, np.float64), option=orjson.OPT_SERIALIZE_NUMPY)
    kinds = Packed.of([msgspec.json.encode(name) for name in names])
    milli = np.rint(np.clip(cover, 0.0, 1.0) * 1000).astype(np.int64)
    buffer, offsets = _splice(
        np.frombuffer(numbers, np.uint8),
        np.frombuffer(f"{AGG_PREFIX}{band}.".encode(), np.uint8),
        np.asarray(indices, np.int64),
        np.asarray(count, np.int64),
        milli,
        np.asarray(kind, np.int64),
        np.asarray(z, np.int64),
        kinds.array,
        kinds.offsets,
        _PARTS.array,
        _PARTS.offsets,
    )
    return Packed(buffer.tobytes(), offsets)


_PARTS = Packed.of(
    [
        b'{"id":"',
        b'","x0":',
        b',"y0":',
        b',"x1":',
        b',"y1":',
        b',"kind":',
        b',"z":',
        b',"agg":{"count":',
        b',"cover":',
        b"}}",
    ]
)


@numba.njit(cache=True, nogil=True)
def _put(out: np.ndarray, k: int, buffer: np.ndarray, offsets: np.ndarray, i: int) -> int:  # pragma: no cover
    """Copy packed part ``i`` to ``out`` at ``k``; where it ends."""
    start, stop = offsets[i], offsets[i + 1]
    copy(out, k, buffer, start, stop - start)
    return k + stop - start


@numba.njit(cache=True, nogil=True)
def _put_int(out: np.ndarray, k: int, value: int) -> int:  # pragma: no cover - compiled
    if value < 0:
        out[k] = 45
        k += 1
        value = -value
    digits = np.empty(20, np.uint8)
    n = 0
    while True:
        digits[n] = 48 + value % 10
        n += 1
        value //= 10
        if value == 0:
            break
    for i in range(n):
        out[k + i] = digits[n - 1 - i]
    return k + n


@numba.njit(cache=True, nogil=True)
def _splice(
    numbers, prefix, indices, count, milli, kind, z, names, name_offsets, parts, part_offsets
):  # pragma: no cover
    """Aggregates as item-shaped JSON objects, packed: ``numbers`` is orjson's ``[[x0,y0,x1,y1],...]``
    of their boxes (shortest round-trip digits), spliced in; cover in thousandths."""
    n = len(indices)
    longest = 0
    for j in range(len(name_offsets) - 1):
        longest = max(longest, name_offsets[j + 1] - name_offsets[j])
    out = np.empty(len(numbers) + n * (160 + len(prefix) + longest), np.uint8)
    offsets = np.empty(n + 1, np.int64)
    k, p = 0, 1  # p: in numbers, past the outer "["
    for i in range(n):
        offsets[i] = k
        k = _put(out, k, parts, part_offsets, 0)
        out[k : k + len(prefix)] = prefix
        k += len(prefix)
        k = _put_int(out, k, indices[i])
        p += 1  # "["
        for c in range(4):
            k = _put(out, k, parts, part_offsets, 1 + c)
            while numbers[p] != 44 and numbers[p] != 93:  # up to "," or "]"
                out[k] = numbers[p]
                k += 1
                p += 1
            p += 1
        p += 1  # "," between rows, or the outer "]"
        k = _put(out, k, parts, part_offsets, 5)
        k = _put(out, k, names, name_offsets, kind[i])
        k = _put(out, k, parts, part_offsets, 6)
        k = _put_int(out, k, z[i])
        k = _put(out, k, parts, part_offsets, 7)
        k = _put_int(out, k, count[i])
        k = _put(out, k, parts, part_offsets, 8)
        m = milli[i]
        if m == 1000 or m == 0:
            out[k] = 49 if m else 48
            k += 1
        else:
            out[k], out[k + 1] = 48, 46  # "0."
            k += 2
            digits, d = m, 100
            while digits:
                out[k] = 48 + digits // d
                k += 1
                digits %= d
                d //= 10
        k = _put(out, k, parts, part_offsets, 9)
    offsets[n] = k
    return out[:k], offsets
