"""Viewport and diff queries: what a client shows, and what changed as it panned."""

from typing import Annotated

import orjson
from fastapi import APIRouter, HTTPException, Query, Response

from spatial import RectLike
from spatial.rect import as_rect

from ..deps import DocumentDep, SettingsDep
from ..documents import Snapshot
from ..responses import JSONBytes, items_array

router = APIRouter(prefix="/documents/{doc}", tags=["viewport"])

Scale = Annotated[float | None, Query(gt=0, description="pixels per canvas unit, for level of detail")]
MinPx = Annotated[float, Query(ge=0, description="leave out items smaller than this many pixels")]
Limit = Annotated[int | None, Query(ge=1, description="most items to return (capped by the server)")]


def _min_size(scale: float | None, min_px: float) -> float:
    """Canvas units below which an item is under ``min_px`` on screen (0: keep everything)."""
    return min_px / scale if scale and min_px else 0.0


def _rect(rect: RectLike, name: str) -> tuple[float, float, float, float]:
    """The library's own validation, as a 422 that says which coordinate is wrong."""
    try:
        return as_rect(rect, name)
    except ValueError as error:
        raise HTTPException(422, str(error)) from None


def _capped(positions, limit: int | None, settings) -> tuple[list, bool]:
    cap = min(limit or settings.default_limit, settings.max_limit)
    return positions[:cap].tolist(), len(positions) > cap


@router.get("/viewport", response_class=JSONBytes)
def read_viewport(
    doc: DocumentDep, settings: SettingsDep,
    x0: float, y0: float, x1: float, y1: float,
    scale: Scale = None, min_px: MinPx = 0.0, limit: Limit = None,
) -> Response:  # fmt: skip
    """Items whose box touches the viewport (closed intervals), at the client's level of detail."""
    rect = _rect((x0, y0, x1, y1), "viewport")
    snap: Snapshot = doc.snapshot
    min_size = _min_size(scale, min_px)
    found = snap.tree.query(rect, min_size=min_size)
    omitted = len(snap.tree.query(rect)) - len(found) if min_size else 0
    shown, truncated = _capped(found, limit, settings)
    head = orjson.dumps({"version": snap.version, "count": len(found), "omitted_small": omitted, "truncated": truncated})
    return JSONBytes(head[:-1] + b',"items":' + items_array(snap.item_json(p) for p in shown) + b"}")


@router.get("/diff", response_class=JSONBytes)
def read_diff(
    doc: DocumentDep, settings: SettingsDep,
    from_: Annotated[str, Query(alias="from", description="old viewport x0,y0,x1,y1", examples=["0,0,1920,1080"])],
    to: Annotated[str, Query(description="new viewport x0,y0,x1,y1", examples=["0,60,1920,1140"])],
    scale: Scale = None, min_px: MinPx = 0.0, from_scale: Scale = None, limit: Limit = None,
) -> Response:  # fmt: skip
    """Items that entered and ids that left between two viewports; stateless, any replica answers."""
    old, new = _rect(from_.split(","), "from"), _rect(to.split(","), "to")
    snap: Snapshot = doc.snapshot
    sizes = (_min_size(from_scale or scale, min_px), _min_size(scale, min_px))
    entered, left = snap.tree.diff(old, new, min_size=sizes)
    shown, truncated = _capped(entered, limit, settings)
    head = orjson.dumps({
        "version": snap.version, "entered": len(entered), "truncated": truncated,
        "leave": [snap.item_id(p) for p in left.tolist()],
    })  # fmt: skip
    return JSONBytes(head[:-1] + b',"enter":' + items_array(snap.item_json(p) for p in shown) + b"}")
