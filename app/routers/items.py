"""Single-item reads and edits: the "mostly static" part."""

from fastapi import APIRouter, Depends, HTTPException, Request, Response, status
from fastapi.concurrency import run_in_threadpool

from ..access import require_read, require_write
from ..deps import DocumentDep, SettingsDep
from ..examples import ITEM, answers
from ..documents import TooMany
from ..items import ItemError, decode_item
from ..responses import JSONBytes

router = APIRouter(prefix="/documents/{doc}/items", tags=["items"], dependencies=[Depends(require_read)])
WRITE = [Depends(require_write)]

EXAMPLE = {**ITEM, "data": {"text": "hello"}}


@router.get("/{item}", response_class=JSONBytes, responses=answers(200, EXAMPLE, 404))
def read_item(doc: DocumentDep, item: str) -> Response:
    """One item."""
    snap = doc.snapshot
    pos = snap.position(item)
    if pos is None:
        raise KeyError(f"item {item!r} not found in document {doc.id!r}")
    return JSONBytes(snap.item_json(pos))


@router.put("/{item}", dependencies=WRITE, responses=answers(200, {"id": "w17", "version": 6}, 401, 403, 404, 413, 422), openapi_extra={"requestBody": {"required": True, "content": {"application/json": {
    "schema": {"type": "object"}, "example": EXAMPLE}}}})  # fmt: skip
async def put_item(doc: DocumentDep, item: str, settings: SettingsDep, request: Request, response: Response) -> dict:
    """Create or replace one item; the body is the item (its ``id`` may be left out)."""
    try:
        parsed = decode_item(await request.body(), settings.max_data_bytes, item_id=item)
    except ItemError as error:
        raise HTTPException(422, str(error)) from None
    try:
        version, created = await run_in_threadpool(doc.put, parsed, settings.max_items)
    except TooMany as error:
        raise HTTPException(413, str(error)) from None
    if created:
        response.status_code = status.HTTP_201_CREATED
    return {"id": item, "version": version}


@router.delete("/{item}", dependencies=WRITE, responses=answers(200, {"id": "w17", "version": 7}, 401, 403, 404))
def delete_item(doc: DocumentDep, item: str) -> dict:
    """Delete one item."""
    try:
        version = doc.delete(item)
    except KeyError:
        raise KeyError(f"item {item!r} not found in document {doc.id!r}") from None
    return {"id": item, "version": version}
