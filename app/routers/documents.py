"""Documents: create, list, describe, delete, and bulk import."""

import logging
import tempfile
from functools import partial
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, status
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, Field

from ..deps import DocumentDep, RegistryDep, SettingsDep
from ..documents import pack
from ..errors import UnsupportedMedia
from ..examples import DOCUMENT, documented
from ..items import decode_ndjson

router = APIRouter(prefix="/documents", tags=["documents"])
log = logging.getLogger("vantage.import")
NDJSON = "application/x-ndjson"


class NewDocument(BaseModel):
    name: str = Field(min_length=1, max_length=200, examples=["Annual report"])


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    responses=documented(
        201, {**DOCUMENT, "version": 0, "items": 0, "bounds": None}, 401, 403, 409, 413, 422
    ),
)
async def create_document(body: NewDocument, registry: RegistryDep) -> dict:
    """Create an empty document."""
    async with registry.store.turn:  # waits on the event loop, holding no thread
        doc = await run_in_threadpool(registry.create, body.name)
    return doc.describe()


@router.get("", responses=documented(200, [DOCUMENT]))
def list_documents(registry: RegistryDep) -> list[dict]:
    """Every document with its item count, bounds and version (opening none of them)."""
    return registry.describe_all()


@router.get("/{doc}", responses=documented(200, DOCUMENT, 404))
def read_document(doc: DocumentDep) -> dict:
    """One document's item count, bounds and version."""
    return doc.describe()


@router.delete(
    "/{doc}", status_code=status.HTTP_204_NO_CONTENT, responses=documented(204, None, 401, 403, 404)
)
async def delete_document(doc: str, registry: RegistryDep) -> None:
    """Delete a document and all its items; its open streams close with code 4404."""
    async with registry.store.turn:
        await run_in_threadpool(registry.delete, doc)


@router.post(
    "/{doc}/items",
    responses=documented(200, {"imported": 1012830, "version": 5}, 401, 403, 404, 408, 413, 415, 422, 507),
    openapi_extra={
        "requestBody": {
            "content": {
                NDJSON: {
                    "schema": {"type": "string"},
                    "example": '{"id": "w17", "x0": 72.0, "y0": 88.0, "x1": 130.5, "y1": 104.0, "kind": "text", "z": 3}\n',
                }
            }
        }
    },
)
async def import_items(
    doc: DocumentDep,
    request: Request,
    settings: SettingsDep,
    mode: Annotated[
        Literal["upsert", "replace"],
        Query(description="upsert: by id, into what the document holds; replace: instead of it"),
    ] = "upsert",
) -> dict:
    """Bulk import NDJSON items (upsert by id, or ``mode=replace``): all or nothing; a bad line
    is named in the 422. ``imported`` counts distinct items (an id given twice is one item: its
    last line wins)."""
    kind = request.headers.get("content-type", "").partition(";")[0].strip().lower()
    if kind != NDJSON:
        raise UnsupportedMedia(
            f"an import's body is NDJSON: send `Content-Type: {NDJSON}`, not {kind or 'none'!r}"
        )
    # Spool the body to disk as it arrives (the guard caps its size and time): a million-line
    # import never sits in memory whole.
    with tempfile.SpooledTemporaryFile(max_size=8 << 20) as body:
        async for chunk in request.stream():
            body.write(chunk)
        size = body.tell()
        body.seek(0)
        # Decoded items cost a few times their bytes: imports take turns (VANTAGE_MAX_IMPORTS).
        async with request.app.state.import_turns:
            log.info("import into %s: decoding %d bytes", doc.id, size)
            batches = decode_ndjson(body, settings.max_line_bytes, settings.max_data_bytes)
            table = await run_in_threadpool(pack, batches)
            async with doc.store.turn:  # other documents' writers queue here, not in the thread pool
                count, version = await doc.write(
                    partial(doc.import_table, replace=mode == "replace"), table, settings.max_items
                )
            del table
            log.info("import into %s: committed version %d", doc.id, version)
    return {"imported": count, "version": version}
