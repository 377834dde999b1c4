"""Examples for the OpenAPI docs at ``/docs``: one per answer, in one place."""

from typing import Any

__all__ = ["DOCUMENT", "ITEM", "documented"]

ITEM = {"id": "w17", "x0": 72.0, "y0": 88.0, "x1": 130.5, "y1": 104.0, "kind": "text", "z": 3}
DOCUMENT = {
    "id": "3f9c2a7b1d04",
    "name": "Annual report",
    "created": 1795000000.0,
    "version": 4,
    "items": 1012830,
    "bounds": [0.0, 0.0, 612.0, 1631208.0],
}

ERRORS = {  # code: (what it means, an example message)
    401: (
        "No token, or (with a JWT key) one that is not valid: expired, forged, malformed; writes (and reads, if so configured) need `Authorization: Bearer <token>`",
        "this needs a token: send `Authorization: Bearer <token>`",
    ),
    403: (
        "A valid token without the grant, or (static tokens only, no JWT key) a token this server does not accept",
        "the token is not one this server accepts",
    ),
    404: ("Unknown document or item", "document '3f9c2a7b1d04' not found"),
    408: ("The body arrived too slowly", "the body took longer than 300 s to arrive (VANTAGE_BODY_TIMEOUT)"),
    409: (
        "The request contradicts the store: a version ahead of the document, or the most documents",
        "since=9 is newer than the document's version 4",
    ),
    413: (
        "Too large: the body, or the items a document would hold",
        "the body exceeds 268435456 bytes, the most this route takes (VANTAGE_MAX_BODY_BYTES)",
    ),
    415: (
        "A body of the wrong type",
        "an import's body is NDJSON: send `Content-Type: application/x-ndjson`, not 'text/plain'",
    ),
    507: (
        "The store is full: nothing was written",
        "the store is full (database or disk is full): nothing was written; free some space",
    ),
    422: ("Invalid input: the message says where and why", "line 2: x0=5.0 > x1=4.0; swap them"),
    503: (
        "Busy, or the store away: try again after Retry-After",
        "1 searches run and 64 wait already (VANTAGE_SEARCH_THREADS, VANTAGE_SEARCH_QUEUE): try again in a moment",
    ),
}


def documented(status: int, example: Any, *errors: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` for a route: its success ``example`` and the errors it can answer."""
    out: dict[int | str, dict[str, Any]] = {status: {"content": {"application/json": {"example": example}}}}
    for code in errors:
        meaning, message = ERRORS[code]
        out[code] = {
            "description": meaning,
            "content": {"application/json": {"example": {"detail": message}}},
        }
    return out
