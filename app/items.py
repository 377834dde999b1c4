"""One canvas item: validation of what clients send, and its JSON form in responses."""

import math
from typing import Any

import orjson

__all__ = ["ItemError", "encode_item", "parse_item"]

FIELDS = ("id", "x0", "y0", "x1", "y1", "kind", "z", "data")


class ItemError(ValueError):
    """An item a client sent is invalid; the message says which field and why."""


def parse_item(raw: Any, max_data_bytes: int, item_id: str | None = None) -> dict[str, Any]:
    """A validated item dict from decoded JSON, or ItemError naming the field.

    ``item_id`` comes from the URL for single-item edits; the body's ``id``, if any, must match.
    """
    if not isinstance(raw, dict):
        raise ItemError(f"an item must be a JSON object, got {type(raw).__name__}")
    unknown = set(raw) - set(FIELDS)
    if unknown:
        raise ItemError(f"unknown field(s) {sorted(unknown)}; allowed: {list(FIELDS)}")
    body_id = raw.get("id", item_id)
    if not isinstance(body_id, str) or not 0 < len(body_id) <= 256:
        raise ItemError("id must be a string of 1 to 256 characters")
    if item_id is not None and body_id != item_id:
        raise ItemError(f"id {body_id!r} in the body does not match {item_id!r} in the URL")
    coords = []
    for name in ("x0", "y0", "x1", "y1"):
        value = raw.get(name)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ItemError(f"{name} must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise ItemError(f"{name} must be finite, got {value}")
        coords.append(value)
    x0, y0, x1, y1 = coords
    if x0 > x1:
        raise ItemError(f"x0={x0} > x1={x1}; swap them")
    if y0 > y1:
        raise ItemError(f"y0={y0} > y1={y1}; swap them")
    kind = raw.get("kind", "box")
    if not isinstance(kind, str) or not 0 < len(kind) <= 32:
        raise ItemError("kind must be a string of 1 to 32 characters")
    z = raw.get("z", 0)
    if isinstance(z, bool) or not isinstance(z, int) or not -(2**31) <= z < 2**31:
        raise ItemError(f"z must be a 32-bit integer, got {z!r}")
    data = raw.get("data")
    data_json = None
    if data is not None:
        if not isinstance(data, dict):
            raise ItemError("data must be a JSON object")
        data_json = orjson.dumps(data)
        if len(data_json) > max_data_bytes:
            raise ItemError(f"data is {len(data_json)} bytes as JSON; the limit is {max_data_bytes}")
    return {"id": body_id, "x0": x0, "y0": y0, "x1": x1, "y1": y1, "kind": kind, "z": z, "data": data_json}


def encode_item(item_id: str, box: tuple[float, ...], kind: str, z: int, data_json: bytes | None) -> bytes:
    """The item's JSON object as sent in responses (floats keep all 17 significant digits)."""
    body = {"id": item_id, "x0": box[0], "y0": box[1], "x1": box[2], "y1": box[3], "kind": kind, "z": z}
    encoded = orjson.dumps(body)
    if data_json is None:
        return encoded
    return encoded[:-1] + b',"data":' + data_json + b"}"
