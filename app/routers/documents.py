"""Documents: create, list, describe, delete, and bulk import."""

import tempfile
from typing import Annotated, Literal

import orjson
from fastapi import APIRouter, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, ConfigDict, Field

from ..access import FULL, Grant
from ..bodies import Lines, import_body
from ..deps import DocumentDep, MediaTypeDep, RegistryDep, SettingsDep
from ..errors import NotFound, UnsupportedMedia, refused_when_full
from ..examples import DOCUMENT, ITEM, documented

__all__ = ["router"]

router = APIRouter(prefix="/documents", tags=["documents"])
NDJSON, JSON = "application/x-ndjson", "application/json"
PAGE = 1000  # documents a page of the list holds, at most
SPOOL_IN_MEMORY = 8 << 20  # bytes of an import's body held in memory; past them, in a file


class NewDocument(BaseModel):
    model_config = ConfigDict(extra="forbid")  # a misspelt field is named, not ignored

    name: str = Field(min_length=1, max_length=200, pattern=r"^[^\x00]*$", examples=["Annual report"])


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


@router.get("", responses=documented(200, [DOCUMENT], 404))
def list_documents(
    registry: RegistryDep,
    request: Request,
    response: Response,
    after: Annotated[
        str | None, Query(description="the last document of the page before: this page starts after it")
    ] = None,
    limit: Annotated[int, Query(ge=1, le=PAGE, description="documents a page holds")] = PAGE,
) -> list[dict]:
    """The documents the token may read, oldest first, with their item counts, bounds and
    versions (opening none of them), ``limit`` a page: when more follow, the ``Link`` header's
    ``rel="next"`` is the next page's URL."""
    grant: Grant = getattr(request.state, "grant", FULL)
    listed = [d for d in registry.describe_all() if grant.reads(d["id"])]
    start = 0
    if after is not None:
        start = next((i + 1 for i, d in enumerate(listed) if d["id"] == after), -1)
        if start < 0:
            raise NotFound(
                f"after={after!r}: no such document in the list (deleted?): list again from the start"
            )
    page = listed[start : start + limit]
    if start + limit < len(listed):
        next_page = request.url.include_query_params(after=page[-1]["id"], limit=limit)
        response.headers["Link"] = f'<{next_page.path}?{next_page.query}>; rel="next"'
    return page


@router.get("/{doc}", responses=documented(200, DOCUMENT, 404))
def read_document(doc: DocumentDep) -> dict:
    """One document's item count, bounds and version."""
    return doc.describe()


@router.delete(
    "/{doc}", status_code=status.HTTP_204_NO_CONTENT, responses=documented(204, None, 401, 403, 404)
)
async def delete_document(doc: str, registry: RegistryDep, request: Request) -> None:
    """Delete a document and all its items (and uploads); its open streams close with code 4404."""
    async with registry.store.turn:
        await run_in_threadpool(registry.delete, doc)
    await run_in_threadpool(request.app.state.uploads.remove_document, doc)


@router.post(
    "/{doc}/items",
    responses=documented(200, {"imported": 1012830, "version": 5}, 401, 403, 404, 408, 413, 415, 422, 507),
    openapi_extra={
        "requestBody": {
            "content": {  # the array first: the docs' "Try it out" sends its example as JSON
                JSON: {"schema": {"type": "array", "items": {"type": "object"}}, "example": [ITEM]},
                NDJSON: {"schema": {"type": "string"}, "example": orjson.dumps(ITEM).decode() + "\n"},
            }
        }
    },
)
async def import_items(
    doc: DocumentDep,
    request: Request,
    settings: SettingsDep,
    kind: MediaTypeDep,
    mode: Annotated[
        Literal["upsert", "replace"],
        Query(description="upsert: by id, into what the document holds; replace: instead of it"),
    ] = "upsert",
) -> dict:
    """Bulk import NDJSON items (upsert by id, or ``mode=replace``): all or nothing; a bad line
    is named in the 422. ``imported`` counts distinct items (an id given twice is one item: its
    last line wins)."""
    if kind not in (NDJSON, JSON):
        raise UnsupportedMedia(
            f"an import's body is NDJSON (`Content-Type: {NDJSON}`) or a JSON array of items "
            f"(`{JSON}`), not {kind or 'none'!r}"
        )
    encoding = request.headers.get("content-encoding", "identity").strip().lower()
    if encoding not in ("identity", "gzip"):
        raise UnsupportedMedia(
            f"an import's body may be gzip-compressed (`Content-Encoding: gzip`), not {encoding!r}"
        )
    # Spool the body to disk as it arrives (the guard caps its size and time): a million-line
    # import never sits in memory whole. In the data directory, beside the import's spill (the
    # system's temp may be small, or another disk), in a file with no name: nothing is left.
    directory = doc.files.directory
    directory.mkdir(parents=True, exist_ok=True)
    with tempfile.SpooledTemporaryFile(max_size=SPOOL_IN_MEMORY, dir=str(directory)) as body:
        lines = Lines(settings.max_line_bytes) if kind == NDJSON and encoding == "identity" else None
        with refused_when_full("spooling the import's body"):
            async for chunk in request.stream():
                if lines is not None:
                    lines.arrived(chunk)
                body.write(chunk)
        body.seek(0)
        inflate = (settings.max_body_bytes, "VANTAGE_MAX_BODY_BYTES")
        turns = request.app.state.import_turns
        return await import_body(
            doc, settings, turns, body, kind == NDJSON, encoding == "gzip", mode, inflate
        )
