"""Single-item reads and edits: the "mostly static" part."""

import asyncio

from fastapi import APIRouter, Request, Response, status

from ..deps import DocumentDep, SettingsDep
from ..documents import Document
from ..errors import NotFound, UnsupportedMedia
from ..examples import ITEM, documented
from ..items import decode_item
from ..responses import JSONBytes

# ``{item:path}``: an id may hold a ``/`` (sent as is or as %2F).
router = APIRouter(prefix="/documents/{doc}/items", tags=["items"])

EXAMPLE = {**ITEM, "data": {"text": "hello"}}


@router.get("/{item:path}", response_class=JSONBytes, responses=documented(200, EXAMPLE, 404))
def read_item(doc: DocumentDep, item: str) -> Response:
    """One item."""
    snap = doc.snapshot
    pos = snap.position(item)
    if pos is None:
        raise NotFound(f"item {item!r} not found in document {doc.id!r}")
    return JSONBytes(snap.item_json(pos))


@router.put(
    "/{item:path}",
    responses=documented(200, {"id": "w17", "version": 6}, 401, 403, 404, 408, 413, 415, 422, 507),
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": {"type": "object"}, "example": EXAMPLE}},
        }
    },
)
async def put_item(
    doc: DocumentDep, item: str, settings: SettingsDep, request: Request, response: Response
) -> dict:
    """Create or replace one item; the body is the item (its ``id`` may be left out)."""
    kind = request.headers.get("content-type", "").partition(";")[0].strip().lower()
    if kind != "application/json":
        raise UnsupportedMedia(
            f"an item is JSON: send `Content-Type: application/json`, not {kind or 'none'!r}"
        )
    parsed = decode_item(await request.body(), settings.max_data_bytes, item_id=item)
    async with doc.store.turn:  # every document's writers queue on the event loop, holding no thread
        version, created = await doc.write(doc.put, parsed, settings.max_items)
    compact_later(request, doc)
    if created:
        response.status_code = status.HTTP_201_CREATED
    return {"id": item, "version": version}


@router.delete("/{item:path}", responses=documented(200, {"id": "w17", "version": 7}, 401, 403, 404, 507))
async def delete_item(doc: DocumentDep, item: str, request: Request) -> dict:
    """Delete one item."""
    async with doc.store.turn:
        version = await doc.write(doc.delete, item)
    compact_later(request, doc)
    return {"id": item, "version": version}


def compact_later(request: Request, doc: Document) -> None:
    """Once enough edits piled up, fold them into a new base, after this answer and in turn
    with other writers: opening the document then maps one file instead of replaying them."""
    if not doc.needs_compaction() or doc.id in (busy := request.app.state.compacting):
        return

    async def compact() -> None:
        try:
            async with doc.store.turn:
                if doc.needs_compaction():
                    await doc.write(doc.compact)
        finally:
            busy.discard(doc.id)

    busy.add(doc.id)
    task = asyncio.get_running_loop().create_task(compact())
    request.app.state.tasks.add(task)
    task.add_done_callback(request.app.state.tasks.discard)
