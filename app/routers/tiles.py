"""Zoomed-out tiles for browsers and CDNs to keep: see :mod:`app.tiles`.

A page zoomed out asks ``/viewport`` or ``/diff`` with ``tiles=true`` for the items and the
tiles its view needs, then fetches each tile it does not hold. A tile's URL with the
``version`` of the answer that named it never changes: it is served ``immutable``; without one,
it is the tile now, to be revalidated (its ETag, then ``304``).
"""

from typing import Annotated

from fastapi import APIRouter, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool

from ..deps import DocumentDep, RegistryDep, SettingsDep
from ..documents import Document
from ..errors import Conflict, Invalid, NotFound
from ..examples import documented
from ..snapshots import Snapshot
from ..tiles import LADDER_STEPS, MAX_DEPTH, MAX_HEIGHT, TileKey, tile_changed_since, within_reach

__all__ = ["router", "tile_answered"]

router = APIRouter(prefix="/documents/{doc}/tiles", tags=["viewport"])

IMMUTABLE = "max-age=31536000, immutable"

EXAMPLE = {
    "band": 3,
    "z": 8,
    "tx": 0,
    "ty": 0,
    "scale": 0.25,
    "box": [0.0, 0.0, 2048.0, 2048.0],
    "size": 512,
    "aggregates": {
        "index": [17],
        "box": [10, 12, 30, 40],
        "count": [42],
        "cover": [310],
        "kind": ["text"],
        "z": [0],
        "boxed": [],
    },
    "layers": {"text": "eNrtwTEBAAAAwqD1T20ND6AAAAAAAAAAAAA4N4NeAAE="},
}


@router.get(
    "/{band}/{z}/{tx}/{ty}",
    responses={
        **documented(200, EXAMPLE, 404, 409, 422),
        304: {"description": "Not Modified: the tile the `If-None-Match` ETag names is still the tile"},
    },
)
async def read_tile(
    doc: DocumentDep,
    settings: SettingsDep,
    registry: RegistryDep,
    request: Request,
    band: Annotated[int, Path(description="the level-of-detail band an answer named", examples=[6])],
    z: Annotated[int, Path(description="the ladder level: its pixels are 2**(z/4) units", examples=[17])],
    tx: Annotated[
        int, Path(description="the tile's column: it spans pixels [tx, tx + 1] * size", examples=[0])
    ],
    ty: Annotated[int, Path(description="the tile's row", examples=[0])],
    version: Annotated[
        int | None,
        Query(
            ge=0,
            description="the version of the answer that named the tile: served immutable (a 409 "
            "when an edit since changed the tile: ask at the version named)",
        ),
    ] = None,
) -> Response:
    """A tile of ``band``'s aggregates: where it is, its aggregates as columns, and each kind's
    pixels their members touch at the ladder scale ``2**(-z/4)`` (``size`` rows of ``size``
    bits, least significant first, deflated, base64). Gzipped once for every client."""
    await registry.catch_up_to(doc, version, settings.catch_up_ms / 1000)
    status, headers, body = await tile_answered(
        doc,
        request.app.state.access.reads_private,
        band,
        z,
        tx,
        ty,
        version,
        request.headers.get("if-none-match", ""),
        request.headers.get("accept-encoding", ""),
    )
    return Response(body, status_code=status, headers=dict(headers))


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
    key = _key(snap, band, z, tx, ty)
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


def _key(snap: Snapshot, band: int, z: int, tx: int, ty: int) -> TileKey:
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
