"""Viewport and diff queries: what a client shows, and what changed as it panned.

The two hot routes are declared here for FastAPI (OpenAPI, validation, error messages) and
answered by :mod:`app.hot` when their query is plainly valid, with the same answer functions
(:func:`app.answers.viewport_answer`, :func:`app.answers.diff_answer`) and the parameters
read from these declarations (``HOT``).
"""

from typing import Annotated

from fastapi import APIRouter, Query, Response

from ..answers import diff_answer, view_of, viewport_answer
from ..deps import DocumentDep, RegistryDep, SettingsDep
from ..examples import ITEM, documented
from ..hot import HotRoute, answered
from ..responses import JSONBytes
from ..snapshots import Snapshot

__all__ = ["HOT", "router"]

router = APIRouter(prefix="/documents/{doc}", tags=["viewport"])
# The routes are async: an answer takes well under a millisecond of compiled work and joins,
# less than a hop to the thread pool and back costs under load.

Scale = Annotated[float | None, Query(gt=0, description="pixels per canvas unit, for level of detail")]
MinPx = Annotated[float, Query(ge=0, description="leave out items smaller than this many pixels")]
Limit = Annotated[int | None, Query(ge=1, description="most items to return (capped by the server)")]
Tiled = Annotated[
    bool,
    Query(
        description="zoomed out, leave the aggregates to tiles: the answer names them (`tiles`: "
        "band, ladder level z, size in pixels, columns and rows) for GET /documents/{doc}/tiles/...",
    ),
]
MinVersion = Annotated[
    int | None,
    Query(
        ge=0,
        description="answer at this version or later (a write's answer names it): a replica "
        "behind it catches up, and when it cannot reach its store within VANTAGE_CATCH_UP_MS "
        "answers 503 with Retry-After; a version never written is a 409",
    ),
]


@router.get(
    "/viewport",
    response_class=JSONBytes,
    responses=documented(
        200,
        {
            "version": 4,
            "band": None,
            "count": 1,
            "aggregates": 0,
            "omitted_small": 0,
            "truncated": False,
            "items": [ITEM],
        },
        404,
        422,
    ),
)
async def read_viewport(
    doc: DocumentDep,
    settings: SettingsDep,
    registry: RegistryDep,
    x0: Annotated[float, Query(examples=[0.0])],
    y0: Annotated[float, Query(examples=[0.0])],
    x1: Annotated[float, Query(examples=[1920.0])],
    y1: Annotated[float, Query(examples=[1080.0])],
    scale: Scale = None,
    min_px: MinPx = 0.0,
    limit: Limit = None,
    tiles: Tiled = False,
    min_version: MinVersion = None,
) -> Response:
    """Items whose box touches the viewport (closed intervals), at the client's level of detail.

    ``count`` is how many items are shown in all; ``omitted_small`` how many more the level of
    detail left out; ``truncated`` says ``items`` holds only the first ``limit`` of them.
    """
    await registry.catch_up_to(doc, min_version, settings.catch_up_ms / 1000)
    return JSONBytes(
        await answered(
            viewport_answer,
            doc,
            settings,
            x0,
            y0,
            x1,
            y1,
            scale=scale,
            min_px=min_px,
            limit=limit,
            tiles=tiles,
        )
    )


@router.get(
    "/diff",
    response_class=JSONBytes,
    responses=documented(
        200,
        {
            "version": 4,
            "band": None,
            "reset": False,
            "entered": 1,
            "truncated": False,
            "leave": ["w3"],
            "enter": [ITEM],
        },
        404,
        409,
        422,
    ),
)
async def read_diff(
    doc: DocumentDep,
    settings: SettingsDep,
    registry: RegistryDep,
    from_: Annotated[
        str, Query(alias="from", description="old viewport x0,y0,x1,y1", examples=["0,0,1920,1080"])
    ],
    to: Annotated[str, Query(description="new viewport x0,y0,x1,y1", examples=["0,60,1920,1140"])],
    scale: Scale = None,
    min_px: MinPx = 0.0,
    limit: Limit = None,
    from_scale: Annotated[
        float | None, Query(gt=0, description="the old viewport's scale, when zooming")
    ] = None,
    since: Annotated[
        int | None, Query(ge=0, description="the version the client holds: edited items are carried too")
    ] = None,
    from_band: Annotated[
        int | None,
        Query(
            description="the `band` of the answer the client holds (its aggregates); default: "
            "the band the old viewport would get now"
        ),
    ] = None,
    tiles: Tiled = False,
    min_version: MinVersion = None,
) -> Response:
    """Items that entered and ids that left between two viewports; stateless, any replica answers.

    With ``since``, items edited after that version come too: in ``enter`` if shown now, else
    in ``leave``. ``reset: true`` means the edits no longer reach back that far: drop what you
    hold and take ``enter`` as the whole view. ``entered`` counts ``enter`` before ``limit``.
    """
    await registry.catch_up_to(doc, min_version, settings.catch_up_ms / 1000)
    return JSONBytes(
        await answered(
            diff_answer,
            doc,
            settings,
            from_,
            to,
            scale=scale,
            min_px=min_px,
            limit=limit,
            from_scale=from_scale,
            since=since,
            from_band=from_band,
            tiles=tiles,
        )
    )


@router.get(
    "/cells",
    tags=["debug"],
    responses=documented(
        200,
        {"version": 4, "cells": [{"depth": 0, "box": [0.0, 0.0, 612.0, 1631208.0], "leaf": False}]},
        404,
        422,
    ),
)
async def read_cells(
    doc: DocumentDep,
    x0: Annotated[float, Query(examples=[0.0])],
    y0: Annotated[float, Query(examples=[0.0])],
    x1: Annotated[float, Query(examples=[1920.0])],
    y1: Annotated[float, Query(examples=[1080.0])],
    limit: Annotated[int, Query(ge=1, le=20_000, description="most cells to return")] = 2000,
) -> dict:
    """The index's nodes touching the viewport, shallowest first: each the union box of its
    items, with its depth and whether it is a leaf. For seeing the structure, not for panning."""
    view = view_of((x0, y0, x1, y1), "viewport")
    snap: Snapshot = doc.snapshot
    cells = snap.tree.cells(view.rect, limit=limit)
    return {
        "version": snap.version,
        "cells": [{"depth": d, "box": box, "leaf": leaf} for d, box, leaf in cells],
    }


# What the fast path (app.hot) answers: each route with the answer function it calls.
HOT = {
    "viewport": HotRoute.of(read_viewport, viewport_answer),
    "diff": HotRoute.of(read_diff, diff_answer),
}
