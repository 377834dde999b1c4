"""The C heap under the numpy arrays and Python objects: what glibc keeps of it once freed."""

from __future__ import annotations

import ctypes
import platform
import sys

__all__ = ["MMAP_THRESHOLD", "map_large_blocks", "return_freed_memory"]

_libc = ctypes.CDLL("libc.so.6") if sys.platform == "linux" and platform.libc_ver()[0] == "glibc" else None


def return_freed_memory() -> None:
    """Hand the heap freed by a bulk load back to the OS: glibc keeps it otherwise, and a
    million-item import would leave the process ~2x its steady size."""
    if _libc is not None:
        _libc.malloc_trim(0)


MMAP_THRESHOLD = 1 << 22  # bytes from which a block of heap is mapped on its own


def map_large_blocks() -> None:
    """Give every block of at least ``MMAP_THRESHOLD`` bytes a map of its own, which goes back
    to the OS when freed. glibc otherwise raises the threshold to the largest block freed so
    far (up to 32 MiB), after which an import's rows of a few MiB, made and freed one after
    another, grow the heap with the document instead of reusing a few rows' worth."""
    if _libc is not None:
        _libc.mallopt(-3, MMAP_THRESHOLD)  # M_MMAP_THRESHOLD; setting it fixes it
        # M_TRIM_THRESHOLD: fixed too by the line above, at 128 KiB, so the heap's top was
        # handed back after nearly every batch and faulted in again (a third of a decode's
        # time). Twice the map threshold, as glibc keeps it while it adjusts both.
        _libc.mallopt(-1, 2 * MMAP_THRESHOLD)
