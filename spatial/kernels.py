"""What compiled code outside ``spatial`` may call: the one ``memcpy``, the read watch, the
type of positions.

The quadtree's hot loops are numba-compiled in ``spatial._kernels`` and ``spatial._walk``
(and ``copy`` in ``spatial._copy``); they stay private, free to change with the tree's layout. This module is
the part of them the service's own compiled loops (over its items' bodies and blocks) are
promised:

- ``copy(dst, dst_at, src, src_at, n)``: ``dst[dst_at:dst_at + n] = src[src_at:src_at + n]``
  as one ``memcpy``, callable only from numba-compiled code, for distinct contiguous 1-d
  arrays of one dtype (others are refused when compiling);
- ``mark_read(marks, pending, places, k, lo, hi)``: report rows ``lo..hi`` of array ``k``
  of a file read, as the tree's walks do (``quadtree.ReadWatch``), with ``UNWATCHED``
  standing for arrays in memory and ``READ_RUN`` the run of blocks a flag of ``pending``
  stands for (it returns how many of those rows' blocks were not checked yet);
- ``index_type(n)``: the type positions below ``n`` are kept in.

These are the objects themselves, not wrappers: numba's cache of a caller's kernel holds
them compiled in, and the wheel's build compiles them where they are defined
(``deploy/build_backend.py``).
"""

from ._copy import copy
from ._kernels import index_type
from ._walk import READ_RUN, UNWATCHED, mark_read

__all__ = ["READ_RUN", "UNWATCHED", "copy", "index_type", "mark_read"]
