"""How items look, for the overview: each item's kind (as a code) and z, and the JSON of the
aggregates that stand in for items too small to draw.

An aggregate goes to clients in an item's shape, with an ``agg`` object that real items never
have, and an id no item can have (item ids may not start with ``~``)::

    {"id": "~6.1207", "x0": 72.0, "y0": 88.0, "x1": 540.0, "y1": 760.0, "kind": "text", "z": 3,
     "agg": {"count": 412, "cover": 0.37}}
"""

from __future__ import annotations

from dataclasses import dataclass, field

import msgspec
import numba
import numpy as np

from spatial.overview import Overview

from .table import Packed, fnv1a

__all__ = ["AGG_PREFIX", "Looks", "agg_id", "agg_json", "parse_agg_id"]

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
    def of(cls, bodies: Packed) -> tuple[Looks, np.ndarray, np.ndarray]:
        """The looks of the items whose response JSON is ``bodies``, and each item's kind code
        and z, ``(looks, kinds, z)``. Cost: one compiled pass over the bytes; a body whose kind
        the pass cannot read plainly (an escape in it) is decoded."""
        buffer = np.frombuffer(bodies.buffer, np.uint8)
        hashes, z, plain = _scan(buffer, bodies.offsets)
        for i in np.flatnonzero(~plain).tolist():  # escapes in the kind: decode those bodies
            look = _look.decode(bodies[i])
            key = msgspec.json.encode(look.kind)[1:-1]
            hashes[i] = fnv1a(np.frombuffer(key, np.uint8), np.array([0, len(key)], np.int64))[0]
            z[i] = look.z
        unique, first, kinds = np.unique(hashes, return_index=True, return_inverse=True)
        names = [_look.decode(bodies[int(i)]).kind for i in first.tolist()]
        if len(set(names)) != len(names):  # two kinds with one hash: name them the slow way
            codes: dict[str, int] = {}
            kinds = np.array(
                [codes.setdefault(_look.decode(bodies[i]).kind, len(codes)) for i in range(len(bodies))]
            )
            names = list(codes)
        return cls(tuple(names), {n: k for k, n in enumerate(names)}), kinds.astype(np.int64), z

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
    """The JSON of ``band``'s aggregates at ``indices``."""
    boxes, count, cover, kind, z = overview.rows(band, indices)
    return [
        b'{"id":"~%d.%d","x0":%r,"y0":%r,"x1":%r,"y1":%r,"kind":%s,"z":%d,"agg":{"count":%d,"cover":%.3g}}'
        % (band, i, x0, y0, x1, y1, msgspec.json.encode(names[k]), zz, c, cv)
        for i, (x0, y0, x1, y1), c, cv, k, zz in zip(
            indices.tolist(),
            boxes.tolist(),
            count.tolist(),
            cover.tolist(),
            kind.tolist(),
            z.tolist(),
            strict=True,
        )
    ]
