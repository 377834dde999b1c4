"""Responses assembled from pre-encoded item JSON: a viewport answer is a join, not a dump."""

from collections.abc import Iterable

from fastapi import Response

__all__ = ["JSONBytes", "items_array"]


class JSONBytes(Response):
    media_type = "application/json"


def items_array(encoded: Iterable[bytes]) -> bytes:
    return b"[" + b",".join(encoded) + b"]"
