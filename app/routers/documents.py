"""Documents: create, list, describe, delete, and bulk import."""

import tempfile

from fastapi import APIRouter, Depends, HTTPException, Request, status
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, Field

from ..access import require_read, require_write
from ..deps import DocumentDep, RegistryDep, SettingsDep
from ..examples import DOCUMENT, answers
from ..documents import TooMany
from ..items import ItemError, decode_ndjson

router = APIRouter(prefix="/documents", tags=["documents"], dependencies=[Depends(require_read)])
WRITE = [Depends(require_write)]


class NewDocument(BaseModel):
    name: str = Field(min_length=1, max_length=200, examples=["Annual report"])


@router.post("", status_code=status.HTTP_201_CREATED, dependencies=WRITE,
             responses=answers(201, {**DOCUMENT, "version": 0, "items": 0, "bounds": None}, 401, 403, 422))
def create_document(body: NewDocument, registry: RegistryDep) -> dict:
    """Create an empty document."""
    return registry.create(body.name).describe()


@router.get("", responses=answers(200, [DOCUMENT]))
def list_documents(registry: RegistryDep) -> list[dict]:
    """Every document with its item count, bounds and version."""
    return [doc.describe() for doc in registry.all()]


@router.get("/{doc}", responses=answers(200, DOCUMENT, 404))
def read_document(doc: DocumentDep) -> dict:
    """One document's item count, bounds and version."""
    return doc.describe()


@router.delete("/{doc}", status_code=status.HTTP_204_NO_CONTENT, dependencies=WRITE,
               responses=answers(204, None, 401, 403, 404))
def delete_document(doc: str, registry: RegistryDep) -> None:
    """Delete a document and all its items."""
    registry.delete(doc)


@router.post(
    "/{doc}/items",
    dependencies=WRITE,
    responses=answers(200, {"imported": 1012830, "version": 5}, 401, 403, 404, 413, 422),
    openapi_extra={"requestBody": {"content": {"application/x-ndjson": {"schema": {"type": "string"},
        "example": '{"id": "w17", "x0": 72.0, "y0": 88.0, "x1": 130.5, "y1": 104.0, "kind": "text", "z": 3}\n'}}}},
)  # fmt: skip
async def import_items(doc: DocumentDep, request: Request, settings: SettingsDep) -> dict:
    """Bulk import NDJSON items (upsert by id): all or nothing; a bad line is named in the 422."""
    # Spool the body to disk as it arrives: a million-line import never sits in memory whole.
    with tempfile.SpooledTemporaryFile(max_size=8 << 20) as body:
        size = 0
        async for chunk in request.stream():
            size += len(chunk)
            if size > settings.max_body_bytes:
                raise HTTPException(413, f"body exceeds {settings.max_body_bytes} bytes (VANTAGE_MAX_BODY_BYTES)")
            body.write(chunk)
        body.seek(0)
        batches = decode_ndjson(body, settings.max_line_bytes, settings.max_data_bytes)
        try:
            count, version = await run_in_threadpool(doc.import_items, batches, settings.max_items)
        except ItemError as error:
            raise HTTPException(422, str(error)) from None
        except TooMany as error:
            raise HTTPException(413, str(error)) from None
    return {"imported": count, "version": version}
