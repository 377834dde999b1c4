"""The C heap under the numpy arrays and Python objects: what glibc keeps of it once freed."""

from __future__ import annotations

import contextlib
import ctypes
import os
import platform
import sys
from pathlib import Path

__all__ = [
    "HUGE_PAGES",
    "MMAP_THRESHOLD",
    "huge_pages_on_request",
    "map_large_blocks",
    "return_freed_memory",
    "with_huge_pages",
]

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


HUGE_PAGES = "glibc.malloc.hugetlb"  # the tunable that has glibc ask for transparent huge pages
_THP = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def huge_pages_on_request() -> bool:
    """Whether the C library is glibc 2.35 or later (which has ``glibc.malloc.hugetlb``) and
    the kernel gives transparent huge pages to the memory asked for them only."""
    version = tuple(int(part) for part in platform.libc_ver()[1].split(".")[:2] if part.isdigit())
    try:
        return _libc is not None and version >= (2, 35) and "[madvise]" in _THP.read_text()
    except OSError:
        return False


def with_huge_pages() -> None:
    """Run this program again from its start, its heap in transparent huge pages (glibc's
    tunable ``glibc.malloc.hugetlb=1``, read only as a program starts), when the kernel gives
    them on request only (``[madvise]``, the usual setting). A large import makes and lets go
    of arrays of 10-100s of MB one after another: numpy asks for huge pages for its own, but
    the compiled kernels' arrays, zstd's and SQLite's buffers were faulted in 4 KiB at a
    time: ~2M faults in a 10M-item import, which takes 0.85x the time without them.
    Nothing when huge pages are off or always on, on a C library other than glibc 2.35 or
    later, or when ``GLIBC_TUNABLES`` names the tunable already (``=0`` keeps them off)."""
    if not sys.executable or HUGE_PAGES in os.environ.get("GLIBC_TUNABLES", ""):
        return
    if not huge_pages_on_request():
        return
    tunables = ":".join(filter(None, (os.environ.get("GLIBC_TUNABLES"), f"{HUGE_PAGES}=1")))
    sys.stdout.flush()
    sys.stderr.flush()
    with contextlib.suppress(OSError):  # not run again: it goes on as it is
        os.execve(sys.executable, sys.orig_argv, {**os.environ, "GLIBC_TUNABLES": tunables})
