"""Zoomed-out tiles for browsers and CDNs to keep: see :mod:`app.tiles`.

A page zoomed out asks ``/viewport`` or ``/diff`` with ``tiles=true`` for the items and the
tiles its view needs, then fetches each tile it does not hold. A tile's URL with the
``version`` of the answer that named it never changes: it is served ``immutable``; without one,
it is the tile now, to be revalidated (its ETag, then ``304``).
"""

from typing import Annotated

from fastapi import APIRouter, Path, Query, Request, Response

from ..answers import tile_answered
from ..deps import DocumentDep, RegistryDep, SettingsDep
from ..examples import documented

__all__ = ["router"]

router = APIRouter(prefix="/documents/{doc}/tiles", tags=["viewport"])

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
