"""Finding text: a phrase, within one item or across consecutive ones, a page of hits at a time."""

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response

from ..deps import DocumentDep
from ..examples import ITEM, documented
from ..responses import JSONBytes
from ..search import Options, answer, search

__all__ = ["router"]

router = APIRouter(prefix="/documents/{doc}", tags=["search"])

EXAMPLE = {
    "version": 4,
    "count": 1,
    "more": False,
    "cursor": None,
    "total": 1,
    "total_exact": True,
    "hits": [
        {
            "ids": ["w17"],
            "box": [80.0, 100.0, 138.5, 112.0],
            "boxes": [[80.0, 100.0, 138.5, 112.0]],
            "text": "Quarterly",
        }
    ],
    "items": [{**ITEM, "data": {"text": "Quarterly"}}],
}


@router.get("/search", response_class=JSONBytes, responses=documented(200, EXAMPLE, 404, 409, 422, 503))
async def search_text(
    doc: DocumentDep,
    request: Request,
    q: Annotated[
        str,
        Query(
            min_length=1,
            max_length=1000,
            description="the text to find: a word or a phrase, which may run across items",
            examples=["quarterly"],
        ),
    ],
    limit: Annotated[int, Query(ge=1, le=1000, description="most hits a page holds")] = 20,
    cursor: Annotated[str | None, Query(description="the `cursor` of the page before: the next page")] = None,
    case: Annotated[Literal["any", "match"], Query(description="match: letters' case as typed")] = "any",
    accents: Annotated[Literal["any", "match"], Query(description="match: accents as typed")] = "any",
    whole: Annotated[
        Literal["any", "words"], Query(description="words: no letter or digit just before or after")
    ] = "any",
) -> Response:
    """Where the text holds ``q``, in document order: each hit's items (``ids``; more than one
    when the phrase runs across consecutive text items), their ``box``, a box for each line
    they lie on (``boxes``: draw these) and their ``text``; ``items`` are the hits' items.
    Case, accents, ligatures, full-width forms, typographic quotes and dashes are folded
    unless asked to match; ``total`` counts every hit, ``cursor`` pages on while ``more``."""
    snap = doc.snapshot
    page = await request.app.state.searches.run(search, snap, q, limit, cursor, Options(case, accents, whole))
    return JSONBytes(answer(snap, page))
