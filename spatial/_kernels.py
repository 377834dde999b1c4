"""The compiled hot loops of the quadtree: Morton keys, the one-pass build, the query walk.

Everything here is numba-compiled (``cache=True``, so a process pays the compile once per
machine) and ``nogil=True``, so threads of a server answer queries on every core. The rest of
the library is plain Python that validates input and calls these with flat arrays.

Layout shared with ``quadtree.py`` (n items, m nodes, in tree order):

- ``boxes[n, 4]`` float64 ``x0, y0, x1, y1`` and ``ids[n]`` int64, permuted so that every node's
  items are one contiguous range; ``alive[n]`` is false for removed items.
- ``nodes[m, 8]``: one 64-byte record per node, so visiting a node touches one cache line.
  Columns ``X0..SMAX`` are float64: the exact union of the node's item boxes (never a cell
  rectangle, so pruning compares stored floats only and no rounding can lose an item) and
  the smallest and largest item size ``max(w, h)`` below it. Columns ``ITEMS`` and
  ``CHILDREN`` hold two int32 each (``lo | hi << 32``, read through an int64 view): the
  node's item range and its child range; a leaf has an empty child range. Nodes are in
  breadth-first order, so a node's children are contiguous and follow it.
"""

import numba as nb
import numpy as np

__all__ = [
    "CHILDREN",
    "HAS_DEAD",
    "INEXACT",
    "ITEMS",
    "MAX_DEPTH",
    "MAX_ITEMS",
    "SMAX",
    "SMIN",
    "X_ORDER",
    "bounds",
    "build",
    "diff",
    "morton_keys",
    "query",
    "sort_by_key",
]

#: Quadrant digits a key holds: 31 bits per axis, so keys fit int64 and sort as signed ints.
MAX_DEPTH = 31

#: Item positions are stored as int32 pairs.
MAX_ITEMS = 2**31 - 1

X0, Y0, X1, Y1, SMIN, SMAX, ITEMS, CHILDREN = range(8)

# Flags of a walk, or-ed together: compile-time constants in the kernels.
HAS_DEAD = 1  # the tree has tombstones: check ``alive``
HAS_OLD = 2  # there is an old viewport: a diff, not a query
INEXACT = 4  # candidates: items of touched leaves come back untested
X_ORDER = 8  # leaves are sorted by x0: a leaf scan stops at the viewport's right edge
_LOW = 0xFFFFFFFF

_STACK = 4 * MAX_DEPTH + 8  # a depth-first walk holds at most 3 pending siblings per level


@nb.njit(cache=True, nogil=True, inline="always")
def _spread(v):
    # Interleave zeros between the low 32 bits of v: bit i moves to bit 2i.
    v &= 0xFFFFFFFF
    v = (v | (v << 16)) & 0x0000FFFF0000FFFF
    v = (v | (v << 8)) & 0x00FF00FF00FF00FF
    v = (v | (v << 4)) & 0x0F0F0F0F0F0F0F0F
    v = (v | (v << 2)) & 0x3333333333333333
    v = (v | (v << 1)) & 0x5555555555555555
    return v


@nb.njit(cache=True, nogil=True)
def morton_keys(boxes, ox, oy, half_side, bits):
    """Quadtree cell key of each box centre in the square (ox, oy, ox + 2 half_side, oy + 2 half_side).

    Each axis is cut into 2**bits cells; a key's top digits name the quadrant at each depth.
    Halving before subtracting keeps centres and offsets finite up to the largest float.
    """
    n = boxes.shape[0]
    keys = np.empty(n, np.int64)
    top = float((1 << bits) - 1)
    scale = float(1 << bits) / half_side if half_side > 0 else 0.0
    for i in range(n):
        cx = (boxes[i, 0] * 0.5 + boxes[i, 2] * 0.5) * 0.5 - ox * 0.5
        cy = (boxes[i, 1] * 0.5 + boxes[i, 3] * 0.5) * 0.5 - oy * 0.5
        qx = int(min(max(cx * scale, 0.0), top))
        qy = int(min(max(cy * scale, 0.0), top))
        keys[i] = (_spread(qy) << 1) | _spread(qx)
    return keys


@nb.njit(cache=True, nogil=True)
def bounds(boxes):
    """``(x0, y0, x1, y1)`` enclosing every box, in one pass (numpy's column min/max stride)."""
    x0, y0, x1, y1 = np.inf, np.inf, -np.inf, -np.inf
    for i in range(boxes.shape[0]):
        x0 = min(x0, boxes[i, 0])
        y0 = min(y0, boxes[i, 1])
        x1 = max(x1, boxes[i, 2])
        y1 = max(y1, boxes[i, 3])
    return x0, y0, x1, y1


@nb.njit(cache=True, nogil=True)
def sort_by_key(keys, boxes):
    """``(order, sorted_keys, sorted_boxes)``: a stable LSD radix sort on the non-negative keys.

    Several times faster than ``np.argsort`` on a million keys in scattered order; passes
    whose digit is the same for every key (the high bits of a small world) are skipped.
    """
    n = keys.shape[0]
    order = np.arange(n)
    k, spare_k = keys.copy(), np.empty_like(keys)
    o, spare_o = order, np.empty_like(order)
    counts = np.empty(1 << 11, np.int64)
    for shift in range(0, 2 * MAX_DEPTH, 11):
        counts[:] = 0
        for i in range(n):
            counts[(k[i] >> shift) & 2047] += 1
        if counts.max() == n:
            continue
        total = 0
        for d in range(counts.shape[0]):
            counts[d], total = total, total + counts[d]
        for i in range(n):
            d = (k[i] >> shift) & 2047
            spare_k[counts[d]] = k[i]
            spare_o[counts[d]] = o[i]
            counts[d] += 1
        k, spare_k = spare_k, k
        o, spare_o = spare_o, o
    sorted_boxes = np.empty_like(boxes)
    for i in range(n):
        sorted_boxes[i] = boxes[o[i]]
    return o, k, sorted_boxes


@nb.njit(cache=True, nogil=True, inline="always")
def _size(boxes, i):
    # In float64 whatever the boxes' type: float32 boxes must size like the nodes built over them.
    return max(
        np.float64(boxes[i, 2]) - np.float64(boxes[i, 0]), np.float64(boxes[i, 3]) - np.float64(boxes[i, 1])
    )


@nb.njit(cache=True, nogil=True)
def _sort_leaf_by_x0(boxes, perm, lo, hi):
    # Insertion sort: leaves are small, and the x0 order lets a scan stop at the query's right edge.
    if hi - lo > 64:
        order = np.argsort(boxes[lo:hi, 0], kind="mergesort") + lo
        boxes[lo:hi] = boxes[order]
        perm[lo:hi] = perm[order]
        return
    for i in range(lo + 1, hi):
        b0, b1, b2, b3, p = boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3], perm[i]
        j = i - 1
        while j >= lo and boxes[j, 0] > b0:
            boxes[j + 1] = boxes[j]
            perm[j + 1] = perm[j]
            j -= 1
        boxes[j + 1, 0], boxes[j + 1, 1], boxes[j + 1, 2], boxes[j + 1, 3] = b0, b1, b2, b3
        perm[j + 1] = p


@nb.njit(cache=True, nogil=True)
def build(keys, boxes, perm, leaf_size, x_order):
    """The node records over items already sorted by key (see the module doc for the layout).

    A node splits at the first quadrant digit where its keys differ, so chains of one-child
    cells are never stored: the node count is at most 2n/leaf_size-ish whatever the extent.
    Identical keys (duplicates, or cells at the float spacing) stay together in one leaf.
    With ``x_order``, each leaf's items (and ``perm``) are reordered by x0 in place.
    """
    n = keys.shape[0]
    cap = max(16, 4 * (n // max(leaf_size, 1)) + 16)
    link = np.empty((cap, 4), np.int64)
    m = 0
    if n > 0:
        link[0, 0], link[0, 1] = 0, n
        m = 1
    i = 0
    while i < m:  # breadth first: the link array is also the work queue
        lo, hi = link[i, 0], link[i, 1]
        link[i, 2] = link[i, 3] = m
        differ = keys[lo] ^ keys[hi - 1]
        if hi - lo > leaf_size and differ != 0:
            top = 63
            while not (differ >> top) & 1:
                top -= 1
            shift = top & ~1  # the quadrant digit where this node's keys first differ
            prefix = (keys[lo] >> (shift + 2)) << (shift + 2)
            start = lo
            for digit in range(1, 5):
                end = lo + np.searchsorted(keys[lo:hi], prefix | digit << shift) if digit < 4 else hi
                if end > start:
                    if m == link.shape[0]:
                        grown = np.empty((2 * m, 4), np.int64)
                        grown[:m] = link[:m]
                        link = grown
                    link[m, 0], link[m, 1] = start, end
                    m += 1
                start = end
            link[i, 3] = m
        elif x_order:
            _sort_leaf_by_x0(boxes, perm, lo, hi)
        i += 1
    nodes = np.empty((m, 8), np.float64)
    packed = nodes.view(np.int64)
    for i in range(m - 1, -1, -1):  # children follow parents, so walk backwards for bottom-up
        lo, hi, clo, chi = link[i, 0], link[i, 1], link[i, 2], link[i, 3]
        if clo == chi:
            bx0, by0, bx1, by1 = np.inf, np.inf, -np.inf, -np.inf
            smin, smax = np.inf, -np.inf
            for j in range(lo, hi):
                bx0 = min(bx0, boxes[j, 0])
                by0 = min(by0, boxes[j, 1])
                bx1 = max(bx1, boxes[j, 2])
                by1 = max(by1, boxes[j, 3])
                s = _size(boxes, j)
                smin = min(smin, s)
                smax = max(smax, s)
        else:
            bx0, by0, bx1, by1 = nodes[clo, X0], nodes[clo, Y0], nodes[clo, X1], nodes[clo, Y1]
            smin, smax = nodes[clo, SMIN], nodes[clo, SMAX]
            for c in range(clo + 1, chi):
                bx0 = min(bx0, nodes[c, X0])
                by0 = min(by0, nodes[c, Y0])
                bx1 = max(bx1, nodes[c, X1])
                by1 = max(by1, nodes[c, Y1])
                smin = min(smin, nodes[c, SMIN])
                smax = max(smax, nodes[c, SMAX])
        nodes[i, X0], nodes[i, Y0], nodes[i, X1], nodes[i, Y1] = bx0, by0, bx1, by1
        nodes[i, SMIN], nodes[i, SMAX] = smin, smax
        packed[i, ITEMS] = lo | (hi << 32)
        packed[i, CHILDREN] = clo | (chi << 32)
    return nodes


@nb.njit(cache=True, nogil=True, inline="always")
def _hits(boxes, i, x0, y0, x1, y1, min_size):
    # Closed intervals: touching counts. Bitwise & rather than `and`: no branch to mispredict
    # on items near the viewport's edge; the size test is loop-invariant, so it is hoisted.
    hit = (boxes[i, 0] <= x1) & (boxes[i, 2] >= x0) & (boxes[i, 1] <= y1) & (boxes[i, 3] >= y0)
    if min_size > 0.0:
        hit &= (np.float64(boxes[i, 2]) - np.float64(boxes[i, 0]) >= min_size) | (
            np.float64(boxes[i, 3]) - np.float64(boxes[i, 1]) >= min_size
        )
    return hit


@nb.njit(cache=True, nogil=True, inline="always")
def _reserve(out, k, more):
    # Grow geometrically so each id is copied O(1) times; callers then write without checks.
    if k + more > out.shape[0]:
        grown = np.empty(2 * (k + more), np.int64)
        grown[:k] = out[:k]
        return grown
    return out


@nb.njit(cache=True, nogil=True, inline="always")
def _take(out, k, ids, alive, has_dead, lo, hi):
    # A whole node qualifies: copy its range, skipping tombstones only when there are any.
    out = _reserve(out, k, hi - lo)
    if has_dead:
        for j in range(lo, hi):
            if alive[j]:
                out[k] = ids[j]
                k += 1
    else:
        out[k : k + hi - lo] = ids[lo:hi]
        k += hi - lo
    return out, k


@nb.njit(cache=True, nogil=True, inline="always")
def _inside(nodes, i, x0, y0, x1, y1):
    return x0 <= nodes[i, X0] and nodes[i, X1] <= x1 and y0 <= nodes[i, Y0] and nodes[i, Y1] <= y1


@nb.njit(cache=True, nogil=True, inline="always")
def _apart(nodes, i, x0, y0, x1, y1):
    return nodes[i, X0] > x1 or nodes[i, X1] < x0 or nodes[i, Y0] > y1 or nodes[i, Y1] < y0


@nb.njit(cache=True, nogil=True, inline="always")
def _strips(out, ax0, ay0, ax1, ay1, bx0, by0, bx1, by1, whole):
    """Closed rects in ``out`` covering closure(A - B) (all of A with ``whole``); returns their count.

    An item in A's answer but not B's touches A outside B, so only nodes touching these
    strips can hold one: a small pan walks two thin strips, not the whole viewport.
    """
    if whole or ax0 > bx1 or ax1 < bx0 or ay0 > by1 or ay1 < by0:
        out[0, 0], out[0, 1], out[0, 2], out[0, 3] = ax0, ay0, ax1, ay1
        return 1
    k = 0
    if ax0 < bx0:  # left of B
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = ax0, ay0, bx0, ay1
        k += 1
    if ax1 > bx1:  # right of B
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = bx1, ay0, ax1, ay1
        k += 1
    mx0, mx1 = max(ax0, bx0), min(ax1, bx1)
    if ay0 < by0:  # below B, between the side strips
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = mx0, ay0, mx1, by0
        k += 1
    if ay1 > by1:  # above B
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = mx0, by1, mx1, ay1
        k += 1
    return k


@nb.njit(cache=True, nogil=True, inline="always")
def _touches_any(nodes, i, strips, count):
    for s in range(count):
        if not _apart(nodes, i, strips[s, 0], strips[s, 1], strips[s, 2], strips[s, 3]):
            return True
    return False


@nb.njit(cache=True, nogil=True, inline="always")
def _relevant(nodes, i, enter, n_enter, new_size, leave, n_leave, old_size):
    # Whether node i may hold an item that enters or, in a diff, leaves.
    if nodes[i, SMAX] >= new_size and _touches_any(nodes, i, enter, n_enter):
        return True
    return n_leave > 0 and nodes[i, SMAX] >= old_size and _touches_any(nodes, i, leave, n_leave)


@nb.njit(cache=True, nogil=True, inline="always")
def _walk(
    nodes,
    boxes,
    ids,
    alive,
    extra_boxes,
    extra_ids,
    n_extra,
    flags,
    nx0,
    ny0,
    nx1,
    ny1,
    new_size,
    ox0,
    oy0,
    ox1,
    oy1,
    old_size,
):
    has_dead, has_old = flags & HAS_DEAD != 0, flags & HAS_OLD != 0
    inexact, x_order = flags & INEXACT != 0, flags & X_ORDER != 0
    packed = nodes.view(np.int64)
    entered = np.empty(1024, np.int64)
    left = np.empty(1024 if has_old else 0, np.int64)
    ke = kl = 0
    small, large = min(old_size, new_size), max(old_size, new_size)
    right_edge = max(nx1, ox1) if has_old else nx1
    # With equal sizes only the strips where the viewports differ can change an answer;
    # a change of level of detail can change it anywhere in either viewport.
    enter, leave = np.empty((4, 4)), np.empty((4, 4))
    n_enter = _strips(enter, nx0, ny0, nx1, ny1, ox0, oy0, ox1, oy1, not has_old or small != large)
    n_leave = _strips(leave, ox0, oy0, ox1, oy1, nx0, ny0, nx1, ny1, small != large) if has_old else 0
    stack = np.empty(_STACK, np.int64)
    sp = 0
    if nodes.shape[0] > 0 and _relevant(nodes, 0, enter, n_enter, new_size, leave, n_leave, old_size):
        stack[0] = 0
        sp = 1
    while sp > 0:  # the stack holds only nodes that may hold an item of either answer
        sp -= 1
        i = stack[sp]
        smin, smax = nodes[i, SMIN], nodes[i, SMAX]
        in_new = _inside(nodes, i, nx0, ny0, nx1, ny1)
        in_old = has_old and _inside(nodes, i, ox0, oy0, ox1, oy1)
        if in_new and in_old and (small == large or smin >= large or smax < small):
            continue  # every item here is in both answers or in neither
        items, children = packed[i, ITEMS], packed[i, CHILDREN]
        lo, hi, clo, chi = items & _LOW, items >> 32, children & _LOW, children >> 32
        # node lies fully inside one viewport and clear of the other: take its whole range, skip tests
        if (
            in_new
            and smin >= new_size
            and not (has_old and smax >= old_size and not _apart(nodes, i, ox0, oy0, ox1, oy1))
        ):
            entered, ke = _take(entered, ke, ids, alive, has_dead, lo, hi)
        elif (
            in_old
            and smin >= old_size
            and not (smax >= new_size and not _apart(nodes, i, nx0, ny0, nx1, ny1))
        ):
            left, kl = _take(left, kl, ids, alive, has_dead, lo, hi)
        elif clo < chi:
            for c in range(chi - 1, clo - 1, -1):  # siblings are adjacent records: test them in one sweep
                if _relevant(nodes, c, enter, n_enter, new_size, leave, n_leave, old_size):
                    stack[sp] = c
                    sp += 1
        elif inexact:
            entered, ke = _take(entered, ke, ids, alive, has_dead, lo, hi)
        else:
            # branch-free compaction: always write, advance only on a hit
            entered = _reserve(entered, ke, hi - lo)
            if x_order:  # leaf is sorted by x0: nothing further right can touch either viewport
                hi = lo + np.searchsorted(boxes[lo:hi, 0], right_edge, side="right")
            if has_old:
                left = _reserve(left, kl, hi - lo)
                for j in range(lo, hi):
                    live = not has_dead or alive[j]
                    hit_new = _hits(boxes, j, nx0, ny0, nx1, ny1, new_size) & live
                    hit_old = _hits(boxes, j, ox0, oy0, ox1, oy1, old_size) & live
                    entered[ke] = left[kl] = ids[j]
                    ke += hit_new > hit_old  # in the new answer only
                    kl += hit_old > hit_new  # in the old answer only
            elif has_dead:
                for j in range(lo, hi):
                    entered[ke] = ids[j]
                    ke += _hits(boxes, j, nx0, ny0, nx1, ny1, new_size) & alive[j]
            else:
                for j in range(lo, hi):
                    entered[ke] = ids[j]
                    ke += _hits(boxes, j, nx0, ny0, nx1, ny1, new_size)
    entered = _reserve(entered, ke, n_extra)
    left = _reserve(left, kl, n_extra if has_old else 0)
    for j in range(n_extra):  # edits not yet merged into the tree
        hit_new = _hits(extra_boxes, j, nx0, ny0, nx1, ny1, new_size)
        hit_old = has_old and _hits(extra_boxes, j, ox0, oy0, ox1, oy1, old_size)
        if hit_new and not hit_old:
            entered[ke] = extra_ids[j]
            ke += 1
        elif hit_old and not hit_new:
            left[kl] = extra_ids[j]
            kl += 1
    return entered, ke, left, kl


@nb.njit(cache=True, nogil=True)
def query(nodes, boxes, ids, alive, extra_boxes, extra_ids, n_extra, flags, x0, y0, x1, y1, min_size):
    """Ids of items touching (x0, y0, x1, y1) whose size is at least ``min_size``.

    With the inexact flag, leaves touching the query come back untested: a superset.
    """
    found, k, _, _ = _walk(
        nodes,
        boxes,
        ids,
        alive,
        extra_boxes,
        extra_ids,
        n_extra,
        flags,
        x0,
        y0,
        x1,
        y1,
        min_size,
        x0,
        y0,
        x1,
        y1,
        min_size,
    )
    return found[:k]


@nb.njit(cache=True, nogil=True)
def diff(
    nodes,
    boxes,
    ids,
    alive,
    extra_boxes,
    extra_ids,
    n_extra,
    flags,
    nx0,
    ny0,
    nx1,
    ny1,
    new_size,
    ox0,
    oy0,
    ox1,
    oy1,
    old_size,
):
    """``(ids, k)``: ``ids[:k]`` entered the new viewport's answer, ``ids[k:]`` left the old's.

    An item is in a viewport's answer when its box touches the viewport and its size is at
    least that viewport's min size. One walk serves both directions: a small pan visits the
    nodes along its edges once, and nodes inside both viewports are skipped untouched.
    """
    entered, ke, left, kl = _walk(
        nodes,
        boxes,
        ids,
        alive,
        extra_boxes,
        extra_ids,
        n_extra,
        flags | HAS_OLD,
        nx0,
        ny0,
        nx1,
        ny1,
        new_size,
        ox0,
        oy0,
        ox1,
        oy1,
        old_size,
    )
    both = np.empty(ke + kl, np.int64)  # one array back to Python: boxing each costs ~0.7 us
    both[:ke] = entered[:ke]
    both[ke:] = left[:kl]
    return both, ke
