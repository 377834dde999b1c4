"""Passes a step at a time (``spatial.paging``): the steps cover every row once, in order,
each within a step of the array; the pages a step read are handed back; the windows of an
array written at random are the budget's held in this thread, whatever another holds."""

import mmap
import threading
from unittest import mock

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from app.stores.base import bounds_of
from spatial import MemoryBudget, _kernels
from spatial.budget import current
from spatial.paging import bounds, release_rows, steps, steps_at, windows


@given(n=st.integers(0, 200), row_bytes=st.integers(1, 64), step_bytes=st.integers(1, 256))
def test_steps_cover_every_row_once_in_order(n, row_bytes, step_bytes):
    with mock.patch("spatial.paging.STEP_BYTES", step_bytes):
        ranges = list(steps(n, row_bytes))
    assert [r for lo, hi in ranges for r in range(lo, hi)] == list(range(n))
    assert all(hi - lo == max(1, step_bytes // row_bytes) for lo, hi in ranges[:-1])


@given(
    rows=st.lists(st.integers(0, 2**31 - 1), max_size=60, unique=True).map(sorted),
    step_bytes=st.integers(1, 2**20),
    dtype=st.sampled_from([np.int32, np.int64]),
)
def test_steps_at_sparse_rows_cover_them_once_each_step_within_a_step_of_rows(rows, step_bytes, dtype):
    """Row numbers up to int32's largest, in int32: a step's bound never wraps around."""
    array = np.array(rows, dtype)
    with mock.patch("spatial.paging.STEP_BYTES", step_bytes):
        ranges = list(steps_at(array, 32))
    step = max(1, step_bytes // 32)
    assert [k for lo, hi in ranges for k in range(lo, hi)] == list(range(len(rows)))
    assert all(hi > lo and rows[hi - 1] - rows[lo] < step for lo, hi in ranges)
    assert all(rows[hi] - rows[lo] >= step for lo, hi in ranges[:-1])  # as long as a step allows


@given(boxes=st.lists(st.tuples(*[st.sampled_from([-0.0, 0.0, -2.5, 3.0, 1e300])] * 4), max_size=30))
def test_bounds_a_step_at_a_time_are_the_bounds_of_one_pass(boxes):
    """To the sign of a zero: the first of equal values is kept, as the one pass keeps it."""
    array = np.array(boxes, np.float64).reshape(-1, 4)
    with mock.patch("spatial.paging.STEP_BYTES", 32):
        stepped = bounds(array)
    assert np.array(stepped).tobytes() == np.array(_kernels.bounds(array)).tobytes()


@given(
    boxes=st.lists(st.tuples(*[st.sampled_from([-0.0, 0.0, -2.5, 3.0, 1e300])] * 4), min_size=1, max_size=40),
    step_bytes=st.sampled_from([32, 96, 1 << 20]),
)
def test_a_documents_bounds_a_step_at_a_time_are_numpys_of_each_whole_side(boxes, step_bytes):
    """The bounds a store keeps and shows (``bounds_of``), read a step at a time, are numpy's
    least and greatest of each whole column, to the sign of a zero."""
    array = np.array(boxes, np.float64).reshape(-1, 4)
    with mock.patch("spatial.paging.STEP_BYTES", step_bytes):
        stepped = bounds_of(array)
    whole = [array[:, 0].min(), array[:, 1].min(), array[:, 2].max(), array[:, 3].max()]
    assert np.array(stepped).tobytes() == np.array(whole).tobytes()


@given(rows=st.integers(0, 100), row_bytes=st.integers(1, 16), window_bytes=st.integers(1, 256))
def test_windows_in_a_file_cover_every_row_once_each_the_budgets(rows, row_bytes, window_bytes):
    with MemoryBudget(window_bytes=window_bytes).held():
        ranges = list(windows(rows, row_bytes, in_file=True))
        in_memory = list(windows(rows, row_bytes, in_file=False))
    assert [r for a, b in ranges for r in range(a, b)] == list(range(rows))
    assert all(b - a == max(1, window_bytes // row_bytes) for a, b in ranges[:-1])
    assert in_memory == ([(0, rows)] if rows else [])


def test_a_budget_held_in_one_thread_leaves_anothers_windows_alone():
    """An import's build and a compaction's in one process each keep their own budget: one
    held while the other's windows are made does not resize them."""
    small, large = MemoryBudget(window_bytes=8), MemoryBudget(window_bytes=800)
    held, go_on, seen = threading.Event(), threading.Event(), []

    def other() -> None:
        with small.held():
            held.set()
            go_on.wait(10)
            seen.append(list(windows(100, 8, in_file=True)))

    thread = threading.Thread(target=other)
    thread.start()
    with large.held():
        held.wait(10)
        mine = list(windows(100, 8, in_file=True))
        go_on.set()
        thread.join(10)
    assert mine == [(0, 100)] and seen == [[(k, k + 1) for k in range(100)]]
    assert current() == MemoryBudget()  # none held past its ``with``


def test_a_steps_pages_are_handed_back_and_read_again_the_same(tmp_path):
    path = tmp_path / "rows"
    data = np.arange(1 << 20, dtype=np.float64)
    path.write_bytes(data.tobytes())
    with open(path, "rb") as file:
        mapped = mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ)
    array = np.frombuffer(mapped, np.float64)
    assert array[:4096].sum() == data[:4096].sum()
    resident = np.zeros(len(mapped) // mmap.PAGESIZE, np.uint8)
    _present(mapped, resident)
    assert resident[:8].all()  # read: mapped into the process
    release_rows(array[:4096])
    _present(mapped, resident)
    assert not resident[:8].any() and np.array_equal(array, data)


def _present(mapped: mmap.mmap, out: np.ndarray) -> None:
    """Which pages of ``mapped`` are mapped into this process now (``/proc/self/pagemap``'s
    present bit; the page cache keeps them either way)."""
    start = np.frombuffer(mapped, np.uint8).ctypes.data
    with open("/proc/self/pagemap", "rb") as pagemap:
        pagemap.seek(start // mmap.PAGESIZE * 8)
        entries = np.frombuffer(pagemap.read(8 * len(out)), np.uint64)
    out[:] = (entries >> np.uint64(63)) & np.uint64(1)
