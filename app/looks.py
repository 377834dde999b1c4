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
import numpy as np

from spatial.overview import Overview

from .table import Packed

__all__ = ["AGG_PREFIX", "Looks", "agg_id", "agg_json", "parse_agg_id"]

AGG_PREFIX = "~"


class _Look(msgspec.Struct):
    kind: str = "box"
    z: int = 0


_looks = msgspec.json.Decoder(list[_Look])
_look = msgspec.json.Decoder(_Look)


@dataclass(frozen=True)
class Looks:
    """Kinds (codes into ``names``) and z of the items a snapshot was built from, and the codes
    of the kinds edits brought since."""

    names: tuple[str, ...]
    kinds: np.ndarray  # (n,) int64 codes, by table position
    z: np.ndarray  # (n,) int64
    codes: dict[str, int] = field(default_factory=dict)

    @classmethod
    def of(cls, bodies: Packed) -> Looks:
        """Read from the items' response JSON. Cost: one decode of the kind and z fields."""
        looks = _looks.decode(b"[" + bodies.join(np.arange(len(bodies))) + b"]") if len(bodies) else []
        codes: dict[str, int] = {}
        kinds = np.fromiter((codes.setdefault(look.kind, len(codes)) for look in looks), np.int64, len(looks))
        z = np.fromiter((look.z for look in looks), np.int64, len(looks))
        return cls(tuple(codes), kinds, z, codes)

    def of_body(self, body: bytes) -> tuple[int, int]:
        """``(kind code, z)`` of one item's JSON (its kind known: see ``with_item``)."""
        look = _look.decode(body)
        return self.codes[look.kind], look.z

    def with_item(self, body: bytes) -> Looks:
        """These looks, knowing the kind of the item ``body`` too."""
        kind = _look.decode(body).kind
        if kind in self.codes:
            return self
        return Looks((*self.names, kind), self.kinds, self.z, {**self.codes, kind: len(self.names)})


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
