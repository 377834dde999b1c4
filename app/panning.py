"""What a panning client must change: the items that entered its view and the ids that left.

One function answers the stateless HTTP ``diff`` and every step of the WebSocket stream. Moving
the view is the index's ``diff``; items edited since the client's version are patched on top
from the snapshot's change log, so a client never keeps a stale box.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import NamedTuple

import msgspec
import numpy as np
import orjson

from spatial.rect import as_rect

from .documents import Snapshot

__all__ = ["Change", "View", "change", "min_size_for"]

Rect = tuple[float, float, float, float]
_NONE = np.empty(0, np.int64)


def min_size_for(scale: float | None, min_px: float) -> float:
    """Canvas units below which an item is under ``min_px`` on screen (0: keep everything).
    An overflow (a tiny scale) means no finite item is big enough: the largest float says so."""
    return min(min_px / scale, sys.float_info.max) if scale and min_px else 0.0


@dataclass(frozen=True)
class View:
    """A viewport and its level of detail: items whose larger side is under ``min_size`` are left out."""

    rect: Rect
    min_size: float = 0.0

    @classmethod
    def of(cls, rect: object, name: str, scale: float | None = None, min_px: float = 0.0) -> View:
        """:raises ValueError: naming ``name`` when the rect is not finite or is inverted"""
        return cls(as_rect(rect, name), min_size_for(scale, min_px))  # type: ignore[arg-type]

    def shows(self, box: Rect) -> bool:
        x0, y0, x1, y1 = self.rect
        touches = box[0] <= x1 and box[2] >= x0 and box[1] <= y1 and box[3] >= y0
        return touches and max(box[2] - box[0], box[3] - box[1]) >= self.min_size


class Change(NamedTuple):
    body: bytes  # the JSON answer
    truncated: bool  # enter was cut at the cap: the client's set is incomplete
    empty: bool  # nothing entered or left


def _shown(snap: Snapshot, pos: int | None, view: View) -> bool:
    """Whether ``view`` shows the item at ``pos`` (None: not in ``snap``)."""
    return pos is not None and view.shows(snap.tree.get(pos))


def change(
    snap: Snapshot, new: View, *, old: View | None = None, since: Snapshot | int | None = None, cap: int,
    extra: dict | None = None,
) -> Change:  # fmt: skip
    """What a client holding ``old`` at version ``since`` needs to show ``new`` at ``snap``.

    ``since`` is the snapshot the client last saw (exact: only items it showed leave), or a
    version number (a stateless caller: every edited item that is not shown now is in ``leave``,
    a no-op for ids the client does not hold). Without ``old``, or when the change log no longer
    reaches back to ``since`` (an import since), or when more than ``cap`` ids would leave, the
    answer is a ``reset``: drop everything, then take ``enter``. No answer lists more than
    ``cap`` items or ids.
    """
    seen = since.version if isinstance(since, Snapshot) else since
    edited = snap.edited_since(seen) if seen is not None else []
    reset = old is None or edited is None
    gone: list[bytes] = []  # JSON ids of edited items that left
    if reset:
        entered, leaving = snap.tree.query(new.rect, min_size=new.min_size), _NONE
    else:
        entered, leaving = snap.tree.diff(old.rect, new.rect, min_size=(old.min_size, new.min_size))
        if edited:
            entered, gone = _patch(snap, edited, entered, leaving, new, old, since)
        if len(leaving) + len(gone) > cap:  # too many ids to list: the client starts over instead
            reset, leaving, gone = True, _NONE, []
            entered = snap.tree.query(new.rect, min_size=new.min_size)
    truncated = len(entered) > cap
    head = orjson.dumps({
        **(extra or {}), "version": snap.version, "reset": reset, "entered": len(entered), "truncated": truncated,
    })  # fmt: skip
    leave = snap.ids_array(leaving, gone)
    body = head[:-1] + b',"leave":' + leave + b',"enter":' + snap.items_array(entered[:cap]) + b"}"
    return Change(body, truncated, not (reset or len(entered) or len(leaving) or gone))


def _patch(
    snap: Snapshot, edited: list[str], entered: np.ndarray, leaving: np.ndarray, new: View, old: View,
    since: Snapshot | int | None,
) -> tuple[np.ndarray, list[bytes]]:  # fmt: skip
    """``entered`` plus the edited items shown now, and the JSON ids of those that left:
    those ``old`` showed in ``since``, or, not knowing it, all not shown and not leaving anyway."""
    fresh, out = set(entered.tolist()), set(leaving.tolist())
    more, gone = [], []
    for item_id in edited:
        pos = snap.position(item_id)
        if _shown(snap, pos, new):
            if pos not in fresh:
                fresh.add(pos)
                more.append(pos)
        elif pos in out:
            continue  # leaving by the index's diff already
        elif not isinstance(since, Snapshot) or _shown(since, since.position(item_id), old):
            gone.append(msgspec.json.encode(item_id))
    return np.concatenate([entered, np.array(more, np.int64)]), gone
