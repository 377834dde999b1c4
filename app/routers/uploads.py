"""Uploads: an import of any size, sent in parts and committed as one (see ``app.uploads``)."""

from dataclasses import asdict
from typing import Annotated, Literal

import orjson
from fastapi import APIRouter, Path, Request, status
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, ConfigDict, Field

from ..bodies import import_body
from ..deps import DocumentDep
from ..errors import NotFound
from ..examples import ITEM, documented
from ..uploads import MAX_PARTS, Upload, Uploads

__all__ = ["router"]

router = APIRouter(prefix="/documents/{doc}/uploads", tags=["uploads"])

UPLOAD = {"id": "7c1e0f4b9a2d4e6f8a0b1c2d3e4f5a6b", "doc": "3f9c2a7b1d04", "format": "ndjson"}
UPLOAD |= {"encoding": "gzip", "mode": "upsert"}
PART = {"number": 1, "bytes": 268435456, "xxh3": "9a0b1c2d3e4f5a6b"}
UploadId = Annotated[str, Path(description="the upload's id, as its creation answered")]


class NewUpload(BaseModel):
    model_config = ConfigDict(extra="forbid")

    format: Literal["ndjson", "json"] = Field(
        "ndjson", description="the body: NDJSON, or a JSON array", examples=["ndjson"]
    )
    encoding: Literal["identity", "gzip"] = Field(
        "identity", description="gzip: the parts, end to end, are one gzip stream", examples=["identity"]
    )
    mode: Literal["upsert", "replace"] = Field(
        "upsert",
        description="upsert: by id, into what the document holds; replace: instead of it",
        examples=["upsert"],
    )


class Commit(BaseModel):
    model_config = ConfigDict(extra="forbid")

    parts: int = Field(ge=1, le=MAX_PARTS, description="how many parts make the body", examples=[1])


def _uploads(request: Request) -> Uploads:
    return request.app.state.uploads


@router.post("", status_code=status.HTTP_201_CREATED, responses=documented(201, UPLOAD, 401, 403, 404, 422))
async def create_upload(doc: DocumentDep, body: NewUpload, request: Request) -> dict:
    """Start an upload: an import too big for one request, its body sent in numbered parts
    (``PUT .../parts/{n}``), then imported all or nothing by ``POST .../commit``."""
    upload = await run_in_threadpool(_uploads(request).new, doc.id, body.format, body.encoding, body.mode)
    return asdict(upload)


@router.get("/{upload}", responses=documented(200, {**UPLOAD, "parts": [PART]}, 401, 403, 404))
async def read_upload(doc: DocumentDep, upload: UploadId, request: Request) -> dict:
    """The upload and the parts received (each with its size and xxh3-64): what to send again
    after an interruption."""
    uploads = _uploads(request)
    found = uploads.get(doc.id, upload)
    parts = await run_in_threadpool(uploads.parts, found)
    return {**asdict(found), "parts": [asdict(p) for p in parts]}


@router.put(
    "/{upload}/parts/{number}",
    responses=documented(200, PART, 401, 403, 404, 408, 413, 422, 507),
    openapi_extra={
        "requestBody": {
            "content": {
                "application/octet-stream": {
                    "schema": {"type": "string", "format": "binary"},
                    "example": orjson.dumps(ITEM).decode() + "\n",
                }
            }
        }
    },
)
async def put_part(
    doc: DocumentDep,
    upload: UploadId,
    number: Annotated[
        int, Path(ge=1, le=MAX_PARTS, description="the part's place in the body", examples=[1])
    ],
    request: Request,
) -> dict:
    """Part ``number`` of the body: any bytes, up to VANTAGE_MAX_BODY_BYTES; it may end
    anywhere (inside a line, inside the gzip stream). Sending a part again replaces it."""
    uploads = _uploads(request)
    found = uploads.get(doc.id, upload)
    try:
        writer = uploads.writer(found, number)
        try:
            async for chunk in request.stream():
                writer.write(chunk)
            part = await run_in_threadpool(writer.keep)
        except BaseException:
            writer.discard()
            raise
    except FileNotFoundError:  # committed, or removed, while the part arrived
        raise NotFound(f"upload {upload!r} was committed or removed while part {number} arrived") from None
    return asdict(part)


@router.post(
    "/{upload}/commit",
    responses=documented(200, {"imported": 1012830, "version": 5}, 401, 403, 404, 409, 413, 422, 507),
)
async def commit_upload(doc: DocumentDep, upload: UploadId, body: Commit, request: Request) -> dict:
    """Import parts 1..``parts``, end to end, all or nothing, as ``POST /documents/{doc}/items``
    would import them in one body (the upload is then gone). A missing part is a 409 naming
    it; a bad line is a 422 naming it (its line number in the whole body), and the upload stays
    to be mended and committed again."""
    uploads = _uploads(request)
    found: Upload = uploads.get(doc.id, upload)
    state = request.app.state
    inflate = (state.settings.max_upload_bytes, "VANTAGE_MAX_UPLOAD_BYTES")
    claim = uploads.claim(found, body.parts)
    try:
        ndjson, gzipped = found.format == "ndjson", found.encoding == "gzip"
        answer = await import_body(
            doc, state.settings, state.import_turns, claim.body, ndjson, gzipped, found.mode, inflate
        )
    except BaseException:
        claim.give_back()
        raise
    await run_in_threadpool(claim.finish)
    return answer


@router.delete(
    "/{upload}", status_code=status.HTTP_204_NO_CONTENT, responses=documented(204, None, 401, 403, 404)
)
async def delete_upload(doc: DocumentDep, upload: UploadId, request: Request) -> None:
    """Give an upload up: its parts are removed, nothing is imported."""
    uploads = _uploads(request)
    await run_in_threadpool(uploads.remove, uploads.get(doc.id, upload))
