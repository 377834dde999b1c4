"""The process's own upkeep, apart from the domain: compiling the kernels before the first
request, keeping start-up's objects out of the garbage collector's way, and handing freed
heap back to the OS after a bulk load."""

import ctypes
import gc
import os
import platform
import sys
import threading
import time
from collections.abc import Callable
from functools import partial

import numpy as np

from spatial import QuadTree
from spatial.overview import Overview

from .looks import Looks, band_json
from .table import ItemTable

__all__ = ["freeze_start_up_objects", "return_freed_memory", "warm_up"]

_say = partial(print, flush=True)
_libc = ctypes.CDLL("libc.so.6") if sys.platform == "linux" and platform.libc_ver()[0] == "glibc" else None


def warm_up(say: Callable[[str], object] = _say, patience: float = 1.0) -> None:
    """Compile the hot kernels now: numba compiles on first call (seconds, when its on-disk
    cache is cold after an install), and that must not land on a client's first request.
    When it takes longer than ``patience`` seconds, ``say`` says so, and how long it took."""
    started = time.monotonic()
    timer = threading.Timer(
        patience,
        say,
        [f"worker {os.getpid()}: compiling the index's kernels (once after an install; about a minute)..."],
    )
    timer.start()
    try:
        _compile()
    finally:
        timer.cancel()
    if time.monotonic() - started > patience:
        say(
            f"worker {os.getpid()}: kernels compiled in {time.monotonic() - started:.0f} s; they are cached now"
        )


def _compile() -> None:
    boxes = np.array([[0.0, 0.0, 1.0, 1.0], [2.0, 2.0, 3.0, 3.0]])
    table = ItemTable.merge([ItemTable.of(["a", "b"], boxes, [b"{}", b"{}"])])
    tree = QuadTree.bulk_load(table.boxes)
    tree.query((0, 0, 1, 1), min_size=0.5)
    tree.diff((0, 0, 1, 1), (1, 1, 3, 3))
    table.bodies.join(tree.query((0, 0, 3, 3)))
    table.position("a")
    looks, kinds, z = Looks.of(table.bodies)
    view = Overview.build(table.boxes, kinds, z)
    band_json(view, looks.names, view.lo)


def return_freed_memory() -> None:
    """Hand the heap freed by a bulk load back to the OS: glibc keeps it otherwise, and a
    million-item import would leave the process ~2x its steady size."""
    if _libc is not None:
        _libc.malloc_trim(0)


def freeze_start_up_objects() -> None:
    """Leave the objects made so far (modules, compiled kernels: ~140k in a worker) out of
    the garbage collector's full passes, which otherwise took ~80 ms scanning them: a stall
    on whichever request or pushed edit was under way. They live as long as the process.
    Call it before the process makes objects that may die (documents, requests)."""
    gc.collect()  # what start-up left as garbage is freed, not kept for good
    gc.freeze()
