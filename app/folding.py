"""A base's items put back in document order with the store's edits since folded in: what a
compaction builds its new base from, and what an import into an edited document merges with.

A base's file lays its items out in its tree's order, each with its place in document order
(its ``rank``). Put back in that order in memory, a 1e8-item base held ~60 bytes an item at
the peak (its boxes placed, the order and its inverse, the ids taken): 6 GB. With a spill
directory, each column is made in a file there and a window of it held at a time: the order
and its inverse, the boxes (each written at its place, a window of places a pass over them in
the order they lie), the ids and the bodies (through buckets, read in the order they lie:
``frames.taken``) and the offsets of the few edited.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from spatial.paging import Scratch, mapping, new_array, placed, release, release_rows, steps, windows

from .frames import places_in, taken
from .table import Edit, ItemTable, scratch_array

__all__ = ["folded"]

LOOKUPS = 256  # lookups of the edited items' ids between two hand-backs of the pages they read


def folded(
    table: ItemTable, edits: Sequence[Edit], rank: np.ndarray | None = None, spill: Path | None = None
) -> ItemTable:
    """``table``'s items in document order (``rank``: each position's place in it; None: as
    they stand) with ``edits`` applied as a merge applies them: each ``(item id, version,
    box, body)`` replaces the item of its id where that stands, or follows the rest, in
    order; one whose box and body are None drops it. The store's edits since a base, the last
    of each item. With ``spill``, a directory: every column made in files there, a window or
    a step of each held at a time (see the module's docstring)."""
    keep, at, added = _changes(table, edits, rank)
    table.release()  # the pages the lookups read (and an open's edits) go back
    scratch = None if spill is None else partial(scratch_array, spill)
    order = _kept_order(rank, keep, scratch)  # each kept item's position, in document order
    del keep
    places = places_in(order, len(table), spill)  # ... and each position's place in it (-1: dropped)
    boxes = new_array(scratch, 4 * (len(order) + len(added)), np.float64).reshape(-1, 4)
    _placed(table.read_boxes(), places, boxes)
    for place, (box, _) in at.items():
        boxes[place] = box
    for k, (_, box, _) in enumerate(added, len(order)):
        boxes[k] = box
    release(boxes)
    if spill is None:
        ids, bodies = table.ids.take(order), table.bodies.take(order)
    else:
        ids, bodies = taken(table.ids, order, spill, places), taken(table.bodies, order, spill, places)
    del order, places
    table.release()
    if at or added:
        bodies = bodies.spliced({p: body for p, (_, body) in at.items()}, [a[2] for a in added], spill)
    if added:
        ids = ids.spliced({}, [msgspec.json.encode(a[0]) for a in added], spill)
    return ItemTable(ids, bodies, boxes)


def _changes(
    table: ItemTable, edits: Sequence[Edit], rank: np.ndarray | None
) -> tuple[np.ndarray, dict[int, tuple[Any, bytes]], list[tuple[str, Any, bytes]]]:
    """``(keep, at, added)``: whether each place in document order stays, the ``(box, body)``
    each edited item takes at its place once the dropped are left out, and the items the edits
    add, ``(id, box, body)``, in order."""
    keep, at, added = np.ones(len(table), bool), {}, []
    for k, (item_id, _, box, body) in enumerate(edits):
        if k % LOOKUPS == LOOKUPS - 1:  # mapped: each lookup's reads map a folio of pages or a few
            table.release()
        pos = table.position(item_id)
        if pos is None:
            if body is not None:
                added.append((item_id, box, body))
            continue
        place = pos if rank is None else int(rank[pos])
        if body is None:
            keep[place] = False
        else:
            at[place] = (box, body)
    dropped = np.flatnonzero(~keep)
    shift = np.searchsorted(dropped, list(at)).tolist()  # the places once those are dropped
    return keep, {place - k: edit for (place, edit), k in zip(at.items(), shift, strict=True)}, added


def _kept_order(rank: np.ndarray | None, keep: np.ndarray, scratch: Scratch | None) -> np.ndarray:
    """The position at each place in document order (``rank`` inverted: a window of it a pass
    over ``rank``), those ``keep`` leaves out dropped, a step at a time (int64, the type the
    takes are compiled for); with ``scratch``, both in its files."""
    inverse = None if rank is None else placed(rank, new_array(scratch, len(rank), np.int64))
    out = new_array(scratch, int(np.count_nonzero(keep)), np.int64)
    k = 0
    for lo, hi in steps(len(keep), 8):
        rows = np.arange(lo, hi) if inverse is None else inverse[lo:hi]
        chosen = rows[keep[lo:hi]]
        made = out[k : k + len(chosen)]
        made[:] = chosen
        release_rows(made)
        release_rows(rows)
        k += len(chosen)
    return out


def _placed(boxes: np.ndarray, places: np.ndarray, out: np.ndarray) -> None:
    """``out[places[p]] = boxes[p]`` for each position ``p`` kept (``places[p] >= 0``). Both
    read in the order they lie, a step at a time, each step's pages of a mapped file handed
    back once copied; with ``out`` in a file, a pass for each window of it: written at random,
    every page of it would be held. A copy in place order would read ``boxes`` at random, and
    hold them all (32 bytes an item) through the copy."""
    for a, b in windows(len(out), out.itemsize * 4, mapping(out) is not None):
        for lo, hi in steps(len(boxes), boxes.itemsize * 4):
            step, rows = places[lo:hi], boxes[lo:hi]
            inside = (step >= a) & (step < b)
            out[step[inside]] = rows[inside]
            release_rows(rows)
            release_rows(step)
        release(out)
