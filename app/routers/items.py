"""Single-item reads and edits: the "mostly static" part."""

from typing import Annotated

import msgspec
import orjson
from fastapi import APIRouter, Path, Request, Response, status
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from ..deps import DocumentDep, MediaTypeDep, SettingsDep
from ..errors import Invalid, NotFound, UnsupportedMedia
from ..examples import ITEM, documented
from ..items import bad_utf8, decode_item
from ..responses import JSONBytes

# ``{item:path}``: an id may hold a ``/`` (sent as is or as %2F).
__all__ = ["router"]

router = APIRouter(prefix="/documents/{doc}/items", tags=["items"])
NDJSON = "application/x-ndjson"
ItemId = Annotated[str, Path(description="the item's id", examples=["w17"])]
EVERYWHERE = (-1.7976931348623157e308,) * 2 + (1.7976931348623157e308,) * 2

EXAMPLE = {**ITEM, "data": {"text": "hello"}}


EXPORT_CHUNK = 16_384  # items a chunk of the export holds


@router.get(
    "",
    response_class=StreamingResponse,
    responses={200: {"content": {NDJSON: {"example": orjson.dumps(EXAMPLE).decode() + "\n"}}}, 404: {}},
)
def export_items(doc: DocumentDep) -> StreamingResponse:
    """Every item as NDJSON, streamed: as an import takes it back (the version in ``Vantage-Version``)."""
    snap = doc.snapshot.unpacked(doc.files.directory)  # one version throughout, whatever lands meanwhile
    positions = snap.in_document_order(snap.tree.query(EVERYWHERE))
    chunks = (snap.ndjson(positions[i : i + EXPORT_CHUNK]) for i in range(0, len(positions), EXPORT_CHUNK))
    return StreamingResponse(chunks, media_type=NDJSON, headers={"vantage-version": str(snap.version)})


class Ids(BaseModel):
    model_config = ConfigDict(extra="forbid")
    ids: list[Annotated[str, Field(min_length=1)]] = Field(min_length=1, examples=[["w17"]])


@router.delete("", responses=documented(200, {"deleted": 2, "version": 8}, 401, 403, 404, 413, 422, 507))
async def delete_items(doc: DocumentDep, body: Ids, request: Request) -> dict:
    """Delete many items at once, all or nothing, as one version; a missing id is a 404
    naming it, and nothing is deleted."""
    ids = list(dict.fromkeys(body.ids))
    version, _ = await doc.write(doc.edit, [(i, None, None) for i in ids])
    request.app.state.compactions.later(doc)
    return {"deleted": len(ids), "version": version}


@router.get("/{item:path}", response_class=JSONBytes, responses=documented(200, EXAMPLE, 404))
def read_item(doc: DocumentDep, item: ItemId) -> Response:
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
    doc: DocumentDep,
    item: ItemId,
    settings: SettingsDep,
    request: Request,
    response: Response,
    kind: MediaTypeDep,
) -> dict:
    """Create or replace one item; the body is the item (its ``id`` may be left out)."""
    if kind != "application/json":
        raise UnsupportedMedia(
            f"an item is JSON: send `Content-Type: application/json`, not {kind or 'none'!r}"
        )
    parsed = decode_item(await request.body(), settings.max_data_bytes, item_id=item)
    version, created = await doc.write(doc.put, parsed, settings.max_items)
    request.app.state.compactions.later(doc)
    if created:
        response.status_code = status.HTTP_201_CREATED
    return {"id": item, "version": version}


@router.patch(
    "/{item:path}",
    responses=documented(200, {"id": "w17", "version": 7}, 401, 403, 404, 408, 413, 415, 422, 507),
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {"schema": {"type": "object"}, "example": {"x0": 80.0, "x1": 138.5}}
            },
        }
    },
)
async def patch_item(
    doc: DocumentDep, item: ItemId, settings: SettingsDep, request: Request, kind: MediaTypeDep
) -> dict:
    """Change some fields of one item, keeping the others (``"data": null`` drops its data);
    ``PUT`` replaces the whole item."""
    if kind not in ("application/json", "application/merge-patch+json"):
        raise UnsupportedMedia(
            f"a patch is JSON: send `Content-Type: application/json`, not {kind or 'none'!r}"
        )
    fields = _object(await request.body())
    if "id" in fields and fields["id"] != item:
        raise Invalid(f"id {fields['id']!r} in the body does not match {item!r} in the URL")
    version = await doc.write(doc.patch, item, fields, settings.max_data_bytes)
    request.app.state.compactions.later(doc)
    return {"id": item, "version": version}


def _object(body: bytes) -> dict:
    try:
        fields = msgspec.json.decode(body)
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as error:
        bad = bad_utf8(body, error)
        raise Invalid(f"the body is not JSON: {f'not valid UTF-8 ({bad})' if bad else error}") from None
    if not isinstance(fields, dict):
        raise Invalid(f"a patch is a JSON object of the fields to change, not {type(fields).__name__}")
    return fields


@router.delete("/{item:path}", responses=documented(200, {"id": "w17", "version": 7}, 401, 403, 404, 507))
async def delete_item(doc: DocumentDep, item: ItemId, request: Request) -> dict:
    """Delete one item."""
    version = await doc.write(doc.delete, item)
    request.app.state.compactions.later(doc)
    return {"id": item, "version": version}
