"""The compiled hot loops of the quadtree: Morton keys, the one-pass build, the query walk.

Everything here is numba-compiled (``cache=True``, so a process pays the compile once per
machine) and ``nogil=True``, so threads of a server answer queries on every core. The rest of
the library is plain Python that validates input and calls these with flat arrays.

Layout shared with ``quadtree.py`` (n items, m nodes, in tree order):

- ``boxes[n, 4]`` float64 ``x0, y0, x1, y1`` and ``ids[n]`` int64, permuted so that every node's
  items are one contiguous range; ``alive[n]`` is false for removed items.
- ``node_box[m, 4]``: the exact union of the node's item boxes (never a cell rectangle, so
  pruning compares stored floats only and no rounding can lose an item).
- ``node_size[m, 2]``: smallest and largest item size ``max(w, h)`` below the node.
- ``node_link[m, 4]``: ``item_lo, item_hi, child_lo, child_hi``; a leaf has ``child_lo == child_hi``.
  Nodes are in breadth-first order, so a node's children are contiguous and follow it.
"""

import numba as nb
import numpy as np

__all__ = [
    "MAX_DEPTH",
    "build",
        "morton_keys",
    "walk",
]

#: Quadrant digits a key holds: 31 bits per axis, so keys fit int64 and sort as signed ints.
MAX_DEPTH = 31

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


@nb.njit(cache=True, nogil=True, inline="always")
def _size(boxes, i):
    return max(boxes[i, 2] - boxes[i, 0], boxes[i, 3] - boxes[i, 1])


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
    """Build the node arrays over items already sorted by key; returns node_box, node_size, node_link.

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
                if digit < 4:
                    end = lo + np.searchsorted(keys[lo:hi], prefix | (digit << shift))
                else:
                    end = hi
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
    link = link[:m].copy()

    node_box = np.empty((m, 4), np.float64)
    node_size = np.empty((m, 2), np.float64)
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
            bx0, by0, bx1, by1 = node_box[clo, 0], node_box[clo, 1], node_box[clo, 2], node_box[clo, 3]
            smin, smax = node_size[clo, 0], node_size[clo, 1]
            for c in range(clo + 1, chi):
                bx0 = min(bx0, node_box[c, 0])
                by0 = min(by0, node_box[c, 1])
                bx1 = max(bx1, node_box[c, 2])
                by1 = max(by1, node_box[c, 3])
                smin = min(smin, node_size[c, 0])
                smax = max(smax, node_size[c, 1])
        node_box[i, 0], node_box[i, 1], node_box[i, 2], node_box[i, 3] = bx0, by0, bx1, by1
        node_size[i, 0], node_size[i, 1] = smin, smax
    return node_box, node_size, link


@nb.njit(cache=True, nogil=True, inline="always")
def _hits(boxes, i, x0, y0, x1, y1, min_size):
    # Closed intervals: touching counts. A NaN-free box of size >= min_size.
    return (
        boxes[i, 0] <= x1
        and boxes[i, 2] >= x0
        and boxes[i, 1] <= y1
        and boxes[i, 3] >= y0
        and (min_size <= 0.0 or _size(boxes, i) >= min_size)
    )


@nb.njit(cache=True, nogil=True, inline="always")
def _push(out, k, value):
    if k == out.shape[0]:
        grown = np.empty(2 * k, np.int64)
        grown[:k] = out
        out = grown
    out[k] = value
    return out, k + 1


@nb.njit(cache=True, nogil=True, inline="always")
def _take(out, k, ids, alive, has_dead, lo, hi):
    # A whole node qualifies: copy its range, skipping tombstones only when there are any.
    if k + hi - lo > out.shape[0]:
        grown = np.empty(2 * (k + hi - lo), np.int64)
        grown[:k] = out[:k]
        out = grown
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
def _inside(bx0, by0, bx1, by1, x0, y0, x1, y1):
    return x0 <= bx0 and bx1 <= x1 and y0 <= by0 and by1 <= y1


@nb.njit(cache=True, nogil=True, inline="always")
def _apart(bx0, by0, bx1, by1, x0, y0, x1, y1):
    return bx0 > x1 or bx1 < x0 or by0 > y1 or by1 < y0


@nb.njit(cache=True, nogil=True)
def walk(
    node_box, node_size, node_link, boxes, ids, alive, has_dead,
    extra_boxes, extra_ids, n_extra,
    nx0, ny0, nx1, ny1, new_size,
    ox0, oy0, ox1, oy1, old_size, has_old,
    exact, x_order,
):  # fmt: skip
    """``(ids, k)``: ``ids[:k]`` entered the new viewport's answer, ``ids[k:]`` left the old's.

    An item is in a viewport's answer when its box touches the viewport and its size is at
    least that viewport's min size. Without ``has_old`` this is a plain query (``k`` is every
    id) and ``exact=False`` returns leaves touching the viewport untested: a superset.
    One walk serves both directions: a small pan visits the nodes along its two edges once.
    The ``extra_*`` items, edits not yet merged into the tree, are scanned linearly.
    """
    entered = np.empty(256, np.int64)
    left = np.empty(16 if not has_old else 256, np.int64)
    ke = kl = 0
    small, large = min(old_size, new_size), max(old_size, new_size)
    stack = np.empty(_STACK, np.int64)
    sp = 0
    if node_link.shape[0] > 0:
        stack[0] = 0
        sp = 1
    while sp > 0:
        sp -= 1
        i = stack[sp]
        bx0, by0, bx1, by1 = node_box[i, 0], node_box[i, 1], node_box[i, 2], node_box[i, 3]
        smin, smax = node_size[i, 0], node_size[i, 1]
        maybe_new = not _apart(bx0, by0, bx1, by1, nx0, ny0, nx1, ny1) and smax >= new_size
        maybe_old = has_old and not _apart(bx0, by0, bx1, by1, ox0, oy0, ox1, oy1) and smax >= old_size
        if not (maybe_new or maybe_old):
            continue
        in_new = _inside(bx0, by0, bx1, by1, nx0, ny0, nx1, ny1)
        in_old = has_old and _inside(bx0, by0, bx1, by1, ox0, oy0, ox1, oy1)
        if in_new and in_old and (small == large or smin >= large or smax < small):
            continue  # every item here is in both answers or in neither
        lo, hi, clo, chi = node_link[i, 0], node_link[i, 1], node_link[i, 2], node_link[i, 3]
        # node lies fully inside one viewport and clear of the other: take its whole range, skip tests
        if in_new and not maybe_old and smin >= new_size:
            entered, ke = _take(entered, ke, ids, alive, has_dead, lo, hi)
        elif in_old and not maybe_new and smin >= old_size:
            left, kl = _take(left, kl, ids, alive, has_dead, lo, hi)
        elif clo == chi:
            if not exact and not has_old:
                entered, ke = _take(entered, ke, ids, alive, has_dead, lo, hi)
                continue
            right_edge = max(nx1, ox1) if has_old else nx1
            for j in range(lo, hi):
                if x_order and boxes[j, 0] > right_edge:
                    break  # leaf is sorted by x0: nothing further right can touch either viewport
                if has_dead and not alive[j]:
                    continue
                hit_new = _hits(boxes, j, nx0, ny0, nx1, ny1, new_size)
                hit_old = has_old and _hits(boxes, j, ox0, oy0, ox1, oy1, old_size)
                if hit_new and not hit_old:
                    entered, ke = _push(entered, ke, ids[j])
                elif hit_old and not hit_new:
                    left, kl = _push(left, kl, ids[j])
        else:
            for c in range(chi - 1, clo - 1, -1):  # reversed, so children pop in tree order
                stack[sp] = c
                sp += 1
    for j in range(n_extra):
        hit_new = _hits(extra_boxes, j, nx0, ny0, nx1, ny1, new_size)
        hit_old = has_old and _hits(extra_boxes, j, ox0, oy0, ox1, oy1, old_size)
        if hit_new and not hit_old:
            entered, ke = _push(entered, ke, extra_ids[j])
        elif hit_old and not hit_new:
            left, kl = _push(left, kl, extra_ids[j])
    if kl == 0:
        return entered[:ke], ke
    both = np.empty(ke + kl, np.int64)  # one array back to Python: boxing each costs ~0.7 us
    both[:ke] = entered[:ke]
    both[ke:] = left[:kl]
    return both, ke
