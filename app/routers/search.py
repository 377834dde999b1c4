"""Finding items by their text."""

from typing import Annotated

import numpy as np
import orjson
from fastapi import APIRouter, Query, Response

from ..deps import DocumentDep
from ..errors import Invalid
from ..examples import ITEM, documented
from ..responses import JSONBytes
from ..search import search

router = APIRouter(prefix="/documents/{doc}", tags=["search"])


@router.get(
    "/search",
    response_class=JSONBytes,
    responses=documented(
        200,
        {"version": 4, "count": 1, "more": False, "items": [{**ITEM, "data": {"text": "Quarterly"}}]},
        404,
        422,
    ),
)
def search_items(
    doc: DocumentDep,
    q: Annotated[
        str,
        Query(
            min_length=1, max_length=200, description="words the text holds, any case", examples=["quarterly"]
        ),
    ],
    limit: Annotated[int, Query(ge=1, le=1000, description="most items to return")] = 20,
) -> Response:
    """Items whose text (``data.text``) holds every word of ``q``, in document order; ``more``
    says there are others past ``limit``."""
    snap = doc.snapshot
    try:
        found, more = search(snap, q, limit)
    except ValueError as error:
        raise Invalid(str(error)) from None
    head = orjson.dumps({"version": snap.version, "count": len(found), "more": more})
    return JSONBytes(snap.items_array(np.array(found, np.int64), ends=(head[:-1] + b',"items":[', b"]}")))
