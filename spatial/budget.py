"""What a build in files (an import's, a compaction's) may hold at once: a ``MemoryBudget``.

The builds in files (``QuadTree.build_arrays`` and ``Overview.build_arrays`` with a scratch,
``sorting.sorted_keys`` with one) hold a few whole structures (the tree's nodes, a band's
rows: a few bytes an item) and, above them, a run at a time: the tree's boxes gathered in its
order (``run_bytes``), an array written at random a window of it at a time (a band's columns,
an order inverted, the items' offsets in the tree's order: ``window_bytes``), keys sorted a
part at a time (``sort_bytes``). A smaller budget holds less and passes over the boxes more
often; the answers are the same whatever the budget.

A budget is a value, not a setting of the process: a build is given one (``budget=``), or
runs under one (``with budget.held():``, which the calls inside it read through
``current()``). The budget held is the calling thread's (and asyncio task's) alone, so two
builds in one process, an import's and a compaction's, each keep their own.

>>> budget = MemoryBudget.of_runs(64 << 20)
>>> (budget.run_bytes, budget.window_bytes, budget.sort_bytes) == (64 << 20, 64 << 20, 16 << 20)
True
>>> with budget.held():
...     current() is budget
True
>>> current() == MemoryBudget()
True
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

__all__ = ["LEAST_RUN_BYTES", "MOST_RUN_BYTES", "MemoryBudget", "current"]

LEAST_RUN_BYTES = 16 << 20  # below it, the passes over the boxes cost more than they save
MOST_RUN_BYTES = 256 << 20  # past it, a run saves no pass worth its memory


@dataclass(frozen=True)
class MemoryBudget:
    """The bytes a build in files holds at once above what it holds whole: the default is
    the most worth holding (``MOST_RUN_BYTES``), ``of_runs`` sizes one to an aim.

    :raises ValueError: if a size is below 1 byte
    """

    #: of the boxes ``QuadTree.build_arrays`` holds at once (a run of whole leaves)
    run_bytes: int = MOST_RUN_BYTES
    #: of an array in a file a pass writes at random (the rest by the passes after it)
    window_bytes: int = MOST_RUN_BYTES
    #: of keys and positions ``sorting.sorted_keys`` sorts in memory at once, in files
    sort_bytes: int = MOST_RUN_BYTES // 4

    def __post_init__(self) -> None:
        for name in ("run_bytes", "window_bytes", "sort_bytes"):
            if getattr(self, name) < 1:
                raise ValueError(f"MemoryBudget({name}={getattr(self, name)}): give 1 byte or more")

    @classmethod
    def of_runs(cls, run_bytes: int) -> MemoryBudget:
        """A budget of runs of about ``run_bytes``, held to ``LEAST_RUN_BYTES`` ..
        ``MOST_RUN_BYTES``: windows as large, sorts a quarter of it.

        >>> MemoryBudget.of_runs(1).run_bytes == LEAST_RUN_BYTES
        True
        """
        run_bytes = min(max(run_bytes, LEAST_RUN_BYTES), MOST_RUN_BYTES)
        return cls(run_bytes, run_bytes, run_bytes // 4)

    @contextmanager
    def held(self) -> Iterator[MemoryBudget]:
        """Within the ``with``, this thread's builds (and its task's) hold this budget
        (``current()``); the one held before comes back after."""
        token = _HELD.set(self)
        try:
            yield self
        finally:
            _HELD.reset(token)


_DEFAULT = MemoryBudget()  # frozen: one value shared by every thread that holds none
_HELD: ContextVar[MemoryBudget] = ContextVar("spatial.budget", default=_DEFAULT)


def current() -> MemoryBudget:
    """The budget this thread's (and task's) builds hold now: the innermost
    ``MemoryBudget.held()``'s, else the default ``MemoryBudget()``. Cost: O(1)."""
    return _HELD.get()
