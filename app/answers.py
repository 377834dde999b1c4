"""Every answer a client gets is built here, from one snapshot: the items in a viewport, and
what changed for a panning client (the HTTP ``diff`` and each step of the stream).

Moving the view is the index's ``diff``; items edited since the version the client holds are
patched on top from the snapshot's change log, so a client never keeps a stale box. No answer
lists more than its cap of items or ids: past it, ``truncated`` says so, and a move whose
``leave`` would pass it becomes a ``reset``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import NamedTuple

import msgspec
import numpy as np
import orjson

from spatial.rect import Rect, as_rect, touches

from .documents import Snapshot

__all__ = ["Change", "Held", "View", "change", "min_size_for", "viewport"]

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
        return touches(box, self.rect) and max(box[2] - box[0], box[3] - box[1]) >= self.min_size


@dataclass(frozen=True)
class Held:
    """What a client holds: ``view`` as of ``version``. ``snapshot`` is that version itself
    when the server knows it (the stream): then only items the client was shown leave. Without
    it (a stateless diff), every edited item not shown now is listed in ``leave``, a no-op for
    ids the client does not hold."""

    view: View
    version: int
    snapshot: Snapshot | None = None


class Change(NamedTuple):
    """What a client must change: ``leave`` and ``enter`` as JSON arrays, and the counts."""

    version: int
    reset: bool  # drop everything first
    entered: int  # items entering, before the cap
    truncated: bool  # enter was cut at the cap: the client's set is incomplete
    leave: bytes
    enter: bytes

    @property
    def empty(self) -> bool:
        return not self.reset and self.leave == b"[]" and self.enter == b"[]"

    def json(self, **head: object) -> bytes:
        """The answer, with ``head`` (a stream's ``type`` and ``seq``) first."""
        fields = orjson.dumps(
            {
                **head,
                "version": self.version,
                "reset": self.reset,
                "entered": self.entered,
                "truncated": self.truncated,
            }
        )
        return fields[:-1] + b',"leave":' + self.leave + b',"enter":' + self.enter + b"}"


def viewport(snap: Snapshot, view: View, cap: int) -> bytes:
    """The ``/viewport`` answer: items ``view`` shows, at most ``cap`` of them, with how many
    there are and how many more the level of detail left out."""
    found = snap.tree.query(view.rect, min_size=view.min_size)
    omitted = len(snap.tree.query(view.rect)) - len(found) if view.min_size else 0
    head = orjson.dumps(
        {
            "version": snap.version,
            "count": len(found),
            "omitted_small": omitted,
            "truncated": len(found) > cap,
        }
    )
    return head[:-1] + b',"items":' + snap.items_array(found[:cap]) + b"}"


def change(snap: Snapshot, new: View, held: Held | None, cap: int) -> Change:
    """What a client holding ``held`` needs to show ``new`` at ``snap``.

    Without ``held``, when the change log no longer reaches back to its version (an import
    since), or when more than ``cap`` ids would leave, the answer is a ``reset``: drop
    everything, then take ``enter``.

    :raises ValueError: if ``held.version`` is newer than ``snap``
    """
    edited = snap.edited_since(held.version) if held is not None else None
    if held is None or edited is None:
        return _reset(snap, new, cap)
    entered, leaving = snap.tree.diff(held.view.rect, new.rect, min_size=(held.view.min_size, new.min_size))
    gone: list[bytes] = []  # JSON ids of edited items that left
    if edited:
        entered, gone = _patch(snap, edited, entered, leaving, new, held)
    if len(leaving) + len(gone) > cap:  # too many ids to list: the client starts over instead
        return _reset(snap, new, cap)
    return Change(
        snap.version,
        False,
        len(entered),
        len(entered) > cap,
        snap.ids_array(leaving, gone),
        snap.items_array(entered[:cap]),
    )


def _reset(snap: Snapshot, new: View, cap: int) -> Change:
    entered = snap.tree.query(new.rect, min_size=new.min_size)
    return Change(
        snap.version, True, len(entered), len(entered) > cap, b"[]", snap.items_array(entered[:cap])
    )


def _shown(snap: Snapshot, pos: int | None, view: View) -> bool:
    """Whether ``view`` shows the item at ``pos`` (None: not in ``snap``)."""
    return pos is not None and view.shows(snap.tree.get(pos))


def _patch(
    snap: Snapshot, edited: list[str], entered: np.ndarray, leaving: np.ndarray, new: View, held: Held
) -> tuple[np.ndarray, list[bytes]]:
    """``entered`` plus the edited items shown now, and the JSON ids of those that left:
    those the client was shown, or, not knowing it, all not shown and not leaving anyway."""
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
        elif held.snapshot is None or _shown(held.snapshot, held.snapshot.position(item_id), held.view):
            gone.append(msgspec.json.encode(item_id))
    return np.concatenate([entered, np.array(more, np.int64)]), gone
