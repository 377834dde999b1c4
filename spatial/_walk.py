"""The compiled walk over a quadtree's arrays: ``query`` and ``diff``.

Numba-compiled (``cache=True``) and ``nogil=True``, so threads of a server answer queries on
every core. ``query`` and ``diff`` take a tree's arrays as one tuple built by ``pack``, then the
walk's flags and the viewports. Helpers are compiled functions of their own, which LLVM
inlines where it pays: with numba's own inlining (``inline="always"``) a fresh compile of every
kernel took 116 s here, not 67, for a walk 2-3% faster.

The tree's ``nodes``, ``boxes`` and ``ids`` are laid out as ``_kernels`` says; besides them:

- ``ids`` None: each item's id is its slot ``0..n-1`` (a snapshot file's tree), stored nowhere.
- ``dead[n]`` uint16 stamps an item removed, 0 while it is not, and a walk sees it removed
  when its stamp is at or past ``horizon`` (see ``quadtree._Tombstones``).
- ``extra_boxes[:n_extra]`` float64 and ``extra_ids[:n_extra]``: inserts not yet built in,
  scanned by every walk; ``gone[n_extra]`` uint16 stamps a row removed, as ``dead`` does (rows
  are only ever added: copies of a tree share them).
- ``marks, pending, places``: what the walk reports reading (see ``quadtree.ReadWatch``). A
  walk marks each block of a file-mapped ``nodes``, ``boxes`` or ``ids`` it reads that is not
  checked yet (``marks[b] |= 2``), counts it in ``pending[0]`` and flags its run of blocks
  (``pending[1 + (b >> READ_RUN)]``); ``places`` is ``shift``,
  then ``offset, row bytes`` of the three arrays in the file. A tree in memory maps every read
  to block 0, marked checked.

A tree that does without a part passes None for it (see ``pack``): its walk is compiled with
no code for that part, chosen by the argument's type (``_by_type``).

Every array variable numba assigns costs two atomic reference-count updates, and the
compiler does not always remove them: when the loops over nodes and items reassigned the
output arrays (to grow them) and handed arrays to helpers, those updates were ~90% of a
small query's time (~3 us of a walk that now takes ~0.4 us on a 1M-item tree). So the
helpers these loops call take scalars and ``(x0, y0, x1, y1)`` tuples, the arrays are read
in place in ``_walk_from``, and only ``_walk`` grows the outputs, between resumed walks.
"""

import numba as nb
import numpy as np
from numba import types
from numba.extending import overload

from ._copy import copy
from ._kernels import CHILDREN, ITEMS, MAX_DEPTH, SMAX, SMIN, X0, X1, Y0, Y1

__all__ = ["HAS_DEAD", "INEXACT", "READ_RUN", "UNWATCHED", "X_ORDER", "diff", "mark_read", "pack", "query"]

# Flags of a walk, or-ed together: compile-time constants in the kernels.
HAS_DEAD = 1  # the tree has tombstones: check ``dead``
HAS_OLD = 2  # there is an old viewport: a diff, not a query
INEXACT = 4  # candidates: items of touched leaves come back untested
X_ORDER = 8  # leaves are sorted by x0: a leaf scan stops at the viewport's right edge
_LOW = 0xFFFFFFFF

_STACK = 4 * MAX_DEPTH + 8  # a depth-first walk holds at most 3 pending siblings per level

_EMPTY = (np.inf, np.inf, -np.inf, -np.inf)  # a strip no box touches: every box has x0 > -inf


def pack(nodes, boxes, ids, edits, watch):
    """The one argument ``query`` and ``diff`` take for a tree, as a plain tuple in this order:
    ``nodes, boxes``; ``ids``, or None for a tree whose ids are its slots; ``edits``, or None
    for a tree with no tombstone and no buffered insert (most trees, which never unpack them:
    each array passed costs a call ~25 ns), else ``(dead, extra_boxes, extra_ids, gone,
    n_extra, horizon)``; ``watch``, what reads are reported to, or None for arrays in memory,
    else ``(marks, pending, places)`` of a ``ReadWatch``.

    A plain tuple rather than a NamedTuple: numba types a plain tuple in its C fast path, a
    NamedTuple through Python (~0.5 us more per call). The arrays are shared, not copied, so
    writes to ``dead``, ``gone`` and the insert buffer's rows are seen by the next walk; build a new
    one when an array is replaced or ``n_extra`` or ``horizon`` changes.
    """
    return (nodes, boxes, ids, edits, watch)


#: Blocks a flag of ``pending`` stands for: who settles the reads scans only flagged runs.
READ_RUN = 12

#: ``(marks, pending, places)`` of arrays in memory: every read falls in block 0, marked checked.
UNWATCHED = (np.ones(1, np.uint8), np.zeros(1, np.int64), np.array([62, 0, 0, 0, 0, 0, 0], np.int64))


@nb.njit(cache=True, nogil=True)
def mark_read(marks, pending, places, k, lo, hi):
    """Report rows ``[lo, hi)`` of array ``k`` read (``places``: ``shift``, then ``offset,
    row bytes`` of each array): mark the blocks of them not checked yet, count them in
    ``pending[0]`` and flag their run of ``2**READ_RUN`` blocks in ``pending[1 + run]``; how
    many there were (``pending[0]`` also counts other threads' reads)."""
    shift, at, row = places[0], places[1 + 2 * k], places[2 + 2 * k]
    unchecked = 0
    for b in range((at + lo * row) >> shift, ((at + hi * row - 1) >> shift) + 1 if hi > lo else 0):
        if marks[b] != 1:
            marks[b] |= 2
            pending[0] += 1
            pending[1 + (b >> READ_RUN)] = 1
            unchecked += 1
    return unchecked


def _by_type(if_none, otherwise, at):
    """A function that compiles as ``if_none`` where the part of its arguments at path ``at``
    (``(0, 4)``: the first argument's fifth member) is None, else as ``otherwise`` (both take
    its arguments): chosen by type when its caller is compiled, so the walk of a tree without a
    part has no code for it. Compiled in, even behind a branch never taken, the read reports
    doubled a query's walk (1.8 -> 3.9 us on the 2000-page document)."""

    def chosen(*args):
        raise NotImplementedError("compiled code only")

    def typer(*args):
        part = args
        for i in at:
            part = part[i]
        return if_none if isinstance(part, types.NoneType) else otherwise

    overload(chosen, strict=False)(typer)
    return chosen


def _unwatched(arrays, k, lo, hi):
    return None


def _watched(arrays, k, lo, hi):
    marks, pending, places = arrays[4]
    mark_read(marks, pending, places, k, lo, hi)


def _slot(ids, j):
    return j


def _stored(ids, j):
    return ids[j]


def _slots_to(out, at, ids, lo, n):
    for j in range(n):
        out[at + j] = lo + j


def _stored_to(out, at, ids, lo, n):
    copy(out, at, ids, lo, n)


def _no_tombstone(edits, j):
    return True


def _not_dead(edits, j):
    return edits[0][j] < edits[5]


def _none_buffered(edits, out, ke, kl, new, new_size, old, old_size, has_old):
    return out, ke, kl


def _buffered(edits, out, ke, kl, new, new_size, old, old_size, has_old):
    _, extra_boxes, extra_ids, gone, n_extra, horizon = edits
    out = _reserve(out, ke, kl, n_extra)
    for j in range(n_extra):  # edits not yet merged into the tree
        if gone[j] >= horizon:  # removed (or moved) since
            continue
        item = extra_boxes[j, 0], extra_boxes[j, 1], extra_boxes[j, 2], extra_boxes[j, 3]
        hit_new = _hits(item, new, new_size)
        hit_old = has_old and _hits(item, old, old_size)
        if hit_new and not hit_old:
            out[ke] = extra_ids[j]
            ke += 1
        elif hit_old and not hit_new:
            kl += 1
            out[out.shape[0] - kl] = extra_ids[j]
    return out, ke, kl


def _false(arrays):
    return False


def _true(arrays):
    return True


# Chosen by the parts of a tree's pack (see ``pack``) when its walk is compiled:
#: ``(arrays, k, lo, hi)``: report rows ``[lo, hi)`` of array ``k`` (0 nodes, 1 boxes, 2 ids) read
_read = _by_type(_unwatched, _watched, at=(0, 4))
#: ``(arrays)``: whether the tree's records come from a file (may be damaged until checked)
_watched_tree = _by_type(_false, _true, at=(0, 4))
#: ``(ids, j)``: built item ``j``'s id
_id = _by_type(_slot, _stored, at=(0,))
#: ``(out, at, ids, lo, n)``: the ids of built items ``lo..lo + n`` to ``out[at:]``
_ids_to = _by_type(_slots_to, _stored_to, at=(2,))
#: ``(edits, j)``: whether built item ``j`` is not removed
_live = _by_type(_no_tombstone, _not_dead, at=(0,))
#: ``(edits, out, ke, kl, new, new_size, old, old_size, has_old)``: the buffered inserts' ids added
_scan_inserts = _by_type(_none_buffered, _buffered, at=(0,))


@nb.njit(cache=True, nogil=True)
def _hits(box, rect, min_size):
    # Closed intervals: touching counts. Bitwise & rather than `and`: no branch to mispredict
    # on items near the viewport's edge; the size test is loop-invariant, so it is hoisted.
    # Sizes in float64 whatever the boxes' type: float32 boxes must size like the nodes built over them.
    b0, b1, b2, b3 = box
    hit = (b0 <= rect[2]) & (b2 >= rect[0]) & (b1 <= rect[3]) & (b3 >= rect[1])
    if min_size > 0.0:
        hit &= (np.float64(b2) - np.float64(b0) >= min_size) | (np.float64(b3) - np.float64(b1) >= min_size)
    return hit


@nb.njit(cache=True, nogil=True)
def _reserve(out, ke, kl, more):
    # Room for ``more`` ids between the entered ids at the front and the left ids at the back.
    # Grow geometrically so each id is copied O(1) times; callers then write without checks.
    if ke + kl + more > out.shape[0]:
        grown = np.empty(2 * (ke + kl + more), np.int64)
        copy(grown, 0, out, 0, ke)
        copy(grown, grown.shape[0] - kl, out, out.shape[0] - kl, kl)
        return grown
    return out


@nb.njit(cache=True, nogil=True)
def _take(out, k, ids, edits, has_dead, lo, hi, back):
    # A whole node qualifies: copy its range, skipping tombstones only when there are any. The
    # ids that entered go to the front of ``out``; with ``back``, those that left go to its back,
    # ``k`` then counting from the end.
    if has_dead:
        for j in range(lo, hi):
            if _live(edits, j):
                out[out.shape[0] - 1 - k if back else k] = _id(ids, j)
                k += 1
    else:
        _ids_to(out, out.shape[0] - k - (hi - lo) if back else k, ids, lo, hi - lo)
        k += hi - lo
    return k


@nb.njit(cache=True, nogil=True)
def _inside(box, rect):
    return rect[0] <= box[0] and box[2] <= rect[2] and rect[1] <= box[1] and box[3] <= rect[3]


@nb.njit(cache=True, nogil=True)
def _apart(box, rect):
    return box[0] > rect[2] or box[2] < rect[0] or box[1] > rect[3] or box[3] < rect[1]


@nb.njit(cache=True, nogil=True)
def _strips(a, b, whole):
    """Four closed rects covering closure(A - B) (all of A with ``whole``), unused ones empty.

    An item in A's answer but not B's touches A outside B, so only nodes touching these
    strips can hold one: a small pan walks two thin strips, not the whole viewport.
    """
    ax0, ay0, ax1, ay1 = a
    bx0, by0, bx1, by1 = b
    if whole or _apart(a, b):
        return a, _EMPTY, _EMPTY, _EMPTY
    mx0, mx1 = max(ax0, bx0), min(ax1, bx1)
    return (
        (ax0, ay0, bx0, ay1) if ax0 < bx0 else _EMPTY,  # left of B
        (bx1, ay0, ax1, ay1) if ax1 > bx1 else _EMPTY,  # right of B
        (mx0, ay0, mx1, by0) if ay0 < by0 else _EMPTY,  # below B, between the side strips
        (mx0, by1, mx1, ay1) if ay1 > by1 else _EMPTY,  # above B
    )


@nb.njit(cache=True, nogil=True)
def _touches_any(box, strips):
    return not (
        _apart(box, strips[0])
        and _apart(box, strips[1])
        and _apart(box, strips[2])
        and _apart(box, strips[3])
    )


@nb.njit(cache=True, nogil=True)
def _relevant(box, smax, enter, new_size, leave, old_size, has_old):
    # Whether a node may hold an item that enters or, in a diff, leaves.
    if smax >= new_size and _touches_any(box, enter):
        return True
    return has_old and smax >= old_size and _touches_any(box, leave)


@nb.njit(cache=True, nogil=True)
def _walk_from(arrays, flags, views, stack, sp, out, ke, kl):
    """Walk the nodes on ``stack[:sp]`` and below, adding the ids that entered after
    ``out[:ke]`` and those that left before ``out[-kl:]`` (one buffer, filled from both ends);
    returns ``(sp, ke, kl, need)``. ``views`` is ``(new, new_size, old, old_size, enter,
    leave)``: the viewports, their min sizes and strips.

    It never grows ``out``, so it is not reassigned inside its loops: when a node needs
    ``need`` more ids than are free it stops, with that node back on the stack, for ``_walk``
    to grow the buffer and call it again.
    """
    nodes, boxes, ids, edits = arrays[0], arrays[1], arrays[2], arrays[3]
    new, new_size, old, old_size, enter, leave = views
    has_dead, has_old = flags & HAS_DEAD != 0, flags & HAS_OLD != 0
    inexact, x_order = flags & INEXACT != 0, flags & X_ORDER != 0
    packed = nodes.view(np.int64)
    small, large = min(old_size, new_size), max(old_size, new_size)
    right_edge = max(new[2], old[2]) if has_old else new[2]
    while sp > 0:  # the stack holds only nodes that may hold an item of either answer
        sp -= 1
        i = stack[sp]
        _read(arrays, 0, i, i + 1)
        box = nodes[i, X0], nodes[i, Y0], nodes[i, X1], nodes[i, Y1]
        smin, smax = nodes[i, SMIN], nodes[i, SMAX]
        in_new = _inside(box, new)
        in_old = has_old and _inside(box, old)
        if in_new and in_old and (small == large or smin >= large or smax < small):
            continue  # every item here is in both answers or in neither
        items, children = packed[i, ITEMS], packed[i, CHILDREN]
        lo, hi, clo, chi = items & _LOW, items >> 32, children & _LOW, children >> 32
        # A record read before its block is checked (see ``_read``) may be damaged: whatever it
        # says, the walk stays within the arrays and goes only down (children follow their
        # parent, at most 4), so it ends; the check then refuses its answer.
        if _watched_tree(arrays):  # records in memory are sound: no checks compiled in (~5% of a walk)
            if not 0 <= lo <= hi <= boxes.shape[0]:
                lo = hi = 0
            if not (i < clo <= chi <= nodes.shape[0] and chi - clo <= 4):
                clo = chi = 0
        if ke + kl + hi - lo > out.shape[0] and (clo == chi or in_new or in_old):
            stack[sp] = i  # it may write all its ids (a node taken whole, a leaf): make room first
            return sp + 1, ke, kl, hi - lo
        # node lies fully inside one viewport and clear of the other: take its whole range, skip tests
        if in_new and smin >= new_size and not (has_old and smax >= old_size and not _apart(box, old)):
            _read(arrays, 2, lo, hi)
            ke = _take(out, ke, ids, edits, has_dead, lo, hi, False)
        elif in_old and smin >= old_size and not (smax >= new_size and not _apart(box, new)):
            _read(arrays, 2, lo, hi)
            kl = _take(out, kl, ids, edits, has_dead, lo, hi, True)
        elif clo < chi:
            _read(arrays, 0, clo, chi)
            for c in range(chi - 1, clo - 1, -1):  # siblings are adjacent records: test them in one sweep
                child = nodes[c, X0], nodes[c, Y0], nodes[c, X1], nodes[c, Y1]
                if _relevant(child, nodes[c, SMAX], enter, new_size, leave, old_size, has_old):
                    stack[sp] = c
                    sp += 1
        elif inexact:
            _read(arrays, 2, lo, hi)
            ke = _take(out, ke, ids, edits, has_dead, lo, hi, False)
        else:
            _read(arrays, 1, lo, hi)
            _read(arrays, 2, lo, hi)
            if x_order:  # leaf is sorted by x0: nothing further right can touch either viewport
                a, b = lo, hi  # binary search for the first x0 > right_edge
                while a < b:
                    mid = (a + b) >> 1
                    if boxes[mid, 0] <= right_edge:
                        a = mid + 1
                    else:
                        b = mid
                hi = a
            # branch-free compaction: always write, advance only on a hit. An item advances
            # ke or kl, never both, so the two ends never cross while ke + kl < len(out).
            if has_old:
                top = out.shape[0] - 1
                for j in range(lo, hi):
                    item = boxes[j, 0], boxes[j, 1], boxes[j, 2], boxes[j, 3]
                    live = not has_dead or _live(edits, j)
                    hit_new = _hits(item, new, new_size) & live
                    hit_old = _hits(item, old, old_size) & live
                    out[ke] = out[top - kl] = _id(ids, j)
                    ke += hit_new > hit_old  # in the new answer only
                    kl += hit_old > hit_new  # in the old answer only
            elif has_dead:
                for j in range(lo, hi):
                    item = boxes[j, 0], boxes[j, 1], boxes[j, 2], boxes[j, 3]
                    out[ke] = _id(ids, j)
                    ke += _hits(item, new, new_size) & _live(edits, j)
            else:
                for j in range(lo, hi):
                    item = boxes[j, 0], boxes[j, 1], boxes[j, 2], boxes[j, 3]
                    out[ke] = _id(ids, j)
                    ke += _hits(item, new, new_size)
    return 0, ke, kl, 0


@nb.njit(cache=True, nogil=True)
def _walk(arrays, flags, new, new_size, old, old_size):
    nodes = arrays[0]
    has_old = flags & HAS_OLD != 0
    small, large = min(old_size, new_size), max(old_size, new_size)
    # With equal sizes only the strips where the viewports differ can change an answer;
    # a change of level of detail can change it anywhere in either viewport.
    enter = _strips(new, old, not has_old or small != large)
    leave = _strips(old, new, small != large) if has_old else enter
    views = new, new_size, old, old_size, enter, leave
    out = np.empty(1024, np.int64)  # entered ids from the front, left ones from the back
    ke = kl = 0
    stack = np.empty(_STACK, np.int64)
    sp = 0
    if nodes.shape[0] > 0:
        _read(arrays, 0, 0, 1)
        root = nodes[0, X0], nodes[0, Y0], nodes[0, X1], nodes[0, Y1]
        if _relevant(root, nodes[0, SMAX], enter, new_size, leave, old_size, has_old):
            stack[0] = 0
            sp = 1
    while sp > 0:
        sp, ke, kl, need = _walk_from(arrays, flags, views, stack, sp, out, ke, kl)
        if sp > 0:  # out of room: grow, then go on from where the walk stopped
            out = _reserve(out, ke, kl, need)
    return _scan_inserts(arrays[3], out, ke, kl, new, new_size, old, old_size, has_old)


@nb.njit(cache=True, nogil=True)
def query(arrays, flags, x0, y0, x1, y1, min_size):
    """Ids of items touching (x0, y0, x1, y1) whose size is at least ``min_size``.

    ``arrays`` is the tree's ``pack``; ``flags`` or-ed walk flags. With ``INEXACT``, leaves
    touching the query come back untested: a superset.
    """
    rect = (x0, y0, x1, y1)
    found, k, _ = _walk(arrays, flags, rect, min_size, rect, min_size)
    return found[:k]


@nb.njit(cache=True, nogil=True)
def diff(arrays, flags, nx0, ny0, nx1, ny1, new_size, ox0, oy0, ox1, oy1, old_size):
    """``(ids, k)``: ``ids[:k]`` entered the new viewport's answer, ``ids[k:]`` left the old's.

    An item is in a viewport's answer when its box touches the viewport and its size is at
    least that viewport's min size. One walk serves both directions: a small pan visits the
    nodes along its edges once, and nodes inside both viewports are skipped untouched.
    """
    new, old = (nx0, ny0, nx1, ny1), (ox0, oy0, ox1, oy1)
    out, ke, kl = _walk(arrays, flags | HAS_OLD, new, new_size, old, old_size)
    # One array back to Python (boxing each costs ~0.3 us): the left ids move down to follow
    # the entered ones; front to back, so an overlap of the two ranges is harmless.
    start = out.shape[0] - kl
    for j in range(kl):
        out[ke + j] = out[start + j]
    return out[: ke + kl], ke
