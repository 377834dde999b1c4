"""How much a build over boxes in files (an import's) holds at once: one size for its runs.

The builds in files (``QuadTree.build_arrays`` and ``Overview.build_arrays`` with a scratch)
hold a few whole structures (the tree's nodes, a band's rows: a few bytes an item) and, above
them, a run at a time: the tree's boxes gathered in its order, an array written at random a
window of it at a time (a band's columns, an order inverted, the items' offsets in the
tree's order), keys sorted a quarter of a run at a time. A smaller run
holds less and passes over the boxes more often.
"""

from __future__ import annotations

from . import _paging, _sorting, quadtree

__all__ = ["LEAST_RUN_BYTES", "MOST_RUN_BYTES", "hold", "held"]

LEAST_RUN_BYTES = 16 << 20  # below it, the passes over the boxes cost more than they save
MOST_RUN_BYTES = 256 << 20  # past it, a run saves no pass worth its memory


def hold(run_bytes: int) -> None:
    """Builds in files hold runs of about ``run_bytes`` from now on, in this process
    (``LEAST_RUN_BYTES`` to ``MOST_RUN_BYTES``)."""
    run_bytes = min(max(run_bytes, LEAST_RUN_BYTES), MOST_RUN_BYTES)
    quadtree.RUN_BYTES = _paging.WINDOW_BYTES = run_bytes
    _sorting.RUN_BYTES = run_bytes // 4


def held() -> int:
    """The run builds in files hold now."""
    return quadtree.RUN_BYTES
