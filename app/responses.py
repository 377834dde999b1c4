"""Responses assembled from pre-encoded JSON: a viewport answer is a join, not a dump."""

from fastapi import Response

__all__ = ["JSONBytes"]


class JSONBytes(Response):
    media_type = "application/json"
