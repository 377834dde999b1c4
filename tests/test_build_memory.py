"""What an index's build holds above its input: the peaks an import reaches at 1e7 items and
beyond. Each measured in a process of its own, its private memory sampled from ``/proc`` while
it builds; glibc is told to map every large block on its own, so a freed array goes back at
once and the samples see what is held, not what the heap kept."""

import mmap
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.table import scratch_array
from spatial import MemoryBudget, QuadTree, scenes
from spatial._kernels import gather_in_place
from spatial.overview import Overview

pytestmark = pytest.mark.usefixtures("scratch_in_files")  # small inputs, mapped paths

ITEMS = 1_000_000

CHILD = textwrap.dedent(
    """
    import functools, os, sys, tempfile, threading, time
    from pathlib import Path
    import numpy as np
    from app.documents import pack
    from app.folding import folded
    from app.frames import framed_arrays, places_in
    from app.looks import Looks
    from app.items import Columns
    from benchmarks.scale import private_bytes
    import app.packed
    import app.table
    import spatial.paging
    from spatial import MemoryBudget, QuadTree, scenes
    from spatial.overview import Overview

    n, spread, what = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
    boxes, _ = scenes.uniform(n, seed=7)  # the board: ~1000 items a screen, spread apart
    boxes[:, 2:] += boxes[:, :2] * (spread - 1)
    boxes[:, :2] *= spread
    kinds, z = np.arange(n, dtype=np.int32) % 4, np.zeros(n, np.int32)

    def batches(boxes, body=b"{}", size=50_000):  # as the decoding processes send them
        for lo in range(0, len(boxes), size):
            ids = [b'"i%d"' % i for i in range(lo, min(lo + size, len(boxes)))]
            ends = np.cumsum([len(i) for i in ids])
            bodies, body_ends = body * len(ids), len(body) * (1 + np.arange(len(ids)))
            yield Columns(b"".join(ids), ends, boxes[lo : lo + size].copy(), bodies, body_ends)

    class Sink:  # where the frames go: counted, not kept
        size = 0

        def write(self, data):
            self.size += len(data)

    spills = []

    def given(n):  # what the build of n items is given, made before it is measured
        if what in ("tree", "overview", "pack"):
            return boxes[:n], kinds[:n], z[:n]
        spills.append(tempfile.TemporaryDirectory())  # a spilled import's table: its columns in files
        spill = Path(spills[-1].name)
        body = b'{"kind":"text","data":{"text":"%s"}}' % (b"x" * 64)
        if what == "looks":  # as an item's body has them: kind and z after the box
            body = b'{"x1":1.0,"kind":"text","z":3,"data":{"text":"%s"}}' % (b"x" * 48)
        table = pack(batches(boxes[:n], body), spill)
        if what == "fold":  # a base's items, laid out in another order than the document's
            assert table.position("i0") == 0  # its id index made (a base's file holds it)
            return table, np.random.default_rng(7).permutation(n).astype(np.int32), spill
        if what in ("frames", "offsets"):
            return table.bodies.unpacked(), np.random.default_rng(7).permutation(n).astype(np.int32), spill
        # A step's pages: ~1 byte an item here, not 16 (the boxes' passes, the bodies')
        spatial.paging.STEP_BYTES = app.packed.STEP_BYTES = 1 << 20
        if what == "looks":  # each item's kind and z read from its body (``Looks.of``)
            return (table.bodies.unpacked(),)
        return table.boxes, kinds[:n], z[:n]  # "mapped tree", "mapped overview": over the table's boxes, mapped

    def build(*args):
        with budget_of(args).held():  # as an import holds one: in this thread, for this build
            return built(*args)

    def budget_of(args):
        if what in ("offsets", "fold", "frames"):  # windows (and steps) of 1 MiB
            spatial.paging.STEP_BYTES = app.packed.STEP_BYTES = 1 << 20
            return MemoryBudget(window_bytes=1 << 20)
        if what == "written tree":  # as an import writes it: a run of its boxes at a time
            return MemoryBudget(run_bytes=1 << 20)
        # A sort in files a sixteenth of its keys at a time (~1 byte an item here, and spread
        # out of place in the warm-up too: compiled before it is measured)
        sort_bytes = 12 * len(args[0]) // 16
        if what == "mapped written tree":  # ... its keys sorted in files too
            return MemoryBudget(run_bytes=1 << 20, sort_bytes=sort_bytes)
        if what == "pack":
            spatial.paging.STEP_BYTES = app.packed.STEP_BYTES = 1 << 20
        return MemoryBudget(sort_bytes=sort_bytes)

    def built(*args):
        if what == "offsets":  # the bodies' offsets in a shuffled order, windows and steps of 1 MiB
            bodies, order, spill = args
            return len(app.packed.offsets_in(bodies.offsets, order, spill, places_in(order, len(bodies), spill)))
        if what == "fold":  # back in document order, a few edits folded in; steps and windows of 1 MiB
            table, rank, spill = args
            box, k = (0.0, 0.0, 1.0, 1.0), len(rank)
            edits = [("i%d" % i, 2, box, b'{"n":1}') for i in range(0, k, k // 1000)]  # as many at any n
            edits += [("i%d" % i, 2, None, None) for i in range(5, k, k // 500)]
            edits += [("new%d" % i, 2, box, b"{}") for i in range(50)]
            return len(folded(table, edits, rank, spill))
        if what == "frames":  # steps and windows of 1 MiB: ~1 byte an item here
            return len(framed_arrays(*args, Sink())["offsets"])
        if what == "written tree":  # as an import writes it: a run of its boxes at a time
            return len(QuadTree.build_arrays(args[0], lambda rows: None)["ids"])
        if what == "mapped written tree":  # as an import builds it: its keys sorted in files too
            scratch = functools.partial(app.table.scratch_array, Path(spills[-1].name))
            return len(QuadTree.build_arrays(args[0], lambda rows: None, scratch=scratch)["ids"])
        if what.endswith("tree"):
            return len(QuadTree.bulk_load(args[0]))
        if what == "looks":  # as an import reads them: the two columns made in files
            return len(Looks.of(args[0], functools.partial(app.table.scratch_array, Path(spills[-1].name)))[1])
        if what == "pack":  # its id index made a step at a time, sorted in files a run at a time
            with tempfile.TemporaryDirectory() as spill:
                return len(pack(batches(args[0]), Path(spill)))
        if what == "mapped overview":  # as an import builds it: homes and the band below in files
            directory = Path(spills[-1].name)
            homes = app.table.scratch_array(directory, len(args[0]), np.int32)
            scratch = functools.partial(app.table.scratch_array, directory)
            return sum(1 for _ in Overview.build_arrays(*args, homes=homes, scratch=scratch))
        return sum(1 for _ in Overview.build_arrays(*args))  # each array let go at once

    build(*given(5000))  # compiled (or loaded from the cache) first
    with app.packed.scratch_in_files():  # ... the paths its arrays in files take too, as n's do
        build(*given(5000))
    args = given(n)
    base, peak, done = private_bytes(os.getpid()), [0], threading.Event()

    def sample():
        while not done.is_set():
            peak[0] = max(peak[0], private_bytes(os.getpid()))
            time.sleep(0.0005)

    sampler = threading.Thread(target=sample)
    sampler.start()
    assert build(*args)
    done.set()
    sampler.join()
    print((peak[0] - base) / n)
    """
)


def _peak_above_input(what: str, spread: float = 1.0, items: int = ITEMS) -> float:
    """Bytes an item that building ``what`` ("tree", "overview", "pack": the table of an
    import's decoded batches, made as they come, "frames": a spilled table's bodies framed
    in a shuffled order, or "mapped tree", "mapped overview": over a spilled table's boxes,
    mapped from its file) over ``items`` boxes held at its peak above them."""
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536")
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(items), str(spread), what],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    return float(done.stdout)


@pytest.mark.slow(seconds=5)  # a build of 1e6 items, in a process of its own
def test_a_trees_build_holds_about_fifty_bytes_an_item_above_its_boxes():
    """The keys (8 bytes an item), the order (8), the boxes in the tree's order (32) and the
    nodes' ranges, then their records (~14): ~50 bytes an item at the peak. It was 69 here
    (80 at 1.6e7 items): the take into the tree's order was buffered into a second copy of
    the boxes, and the keys were held while the node records were made (then copied, to
    align them)."""
    per_item = _peak_above_input("tree")
    assert 32 < per_item < 64, per_item  # above 32: the samples saw the build at all


@pytest.mark.slow(seconds=10)  # two builds of 1e6 items or more, each in a process
def test_builds_over_an_imports_mapped_boxes_hold_a_step_of_them_not_all():
    """An import's boxes are in a file, mapped (``ItemTable.spilled``): the tree's and the
    overview's builds read them a step at a time, each step's pages handed back, so their
    peaks hold what the builds make (~43-47 and ~14 bytes an item here), not the boxes too
    (32 more, as a pass reading them whole would hold, or a gather of them in the tree's
    order). The overview (built as an import builds it: the items' homes and first bands, a
    band's joining items, owners, group order, areas, kinds and parents, its boxes, ids,
    counts and z once its tree is built, and the band below in files) held ~50: its
    elements' counts, z and kinds made beside their areas, and the areas gathered whole to
    be summed; then ~45: each band's cells made in float columns, and the band below's tree
    held beside its boxes gathered for the next; then ~36: its cells' sort held a copy of
    the cells and their order; then ~33: each item's size and first band (8 and 2 bytes)
    were made whole before the first band, and the first bands held; then ~25: a band's
    columns held in memory; then ~21: its boxes, ids, counts and z; then ~17: the band
    below's columns copied into files they were in already."""
    tree, overview = _peak_above_input("mapped tree"), _peak_above_input("mapped overview")
    assert 32 < tree < 56, tree  # above 32: the samples saw the build at all
    assert 10 < overview < 22, overview


@pytest.mark.slow(seconds=5)  # a build of 1e6 items, in a process of its own
def test_a_tree_built_to_be_written_holds_a_run_of_its_boxes_not_all():
    """An import's tree is built to be written (``QuadTree.build_arrays``): its boxes in the
    tree's order are made a run of whole leaves at a time, each written and let go, so the
    build holds its keys' sort at most (the keys and their order, sorted in place: ~17 bytes
    an item with the nodes' ranges), not the boxes in its order (32) beside their places and
    its order (~43 here as ``bulk_load`` builds it). Its sort held ~24 with a copy of each."""
    per_item = _peak_above_input("written tree")
    assert 8 < per_item < 22, per_item  # above 8: the samples saw the sort at all


@pytest.mark.slow(seconds=5)  # a build of 1e6 items, in a process of its own
def test_a_tree_built_in_files_holds_a_run_of_its_keys_not_all():
    """As an import builds it (``build_arrays`` with a scratch), the tree's keys and their
    order are made in files and sorted there a run at a time (``sorted_keys``), then split a
    step of them at a time: it holds its nodes and a run, ~10-11 bytes an item here, where
    the keys sorted in one run hold ~17-22 (and 12 bytes an item in memory at 1e8: 1.2 GB)."""
    per_item = _peak_above_input("mapped written tree")
    assert 4 < per_item < 14, per_item


@pytest.mark.slow(seconds=5)  # a build of 1e6 items, in a process of its own
def test_reading_an_imports_kinds_and_z_holds_two_steps_scans():
    """``Looks.of`` over a spilled import's bodies codes each step's kinds as it scans them,
    into files as an import makes them (each step's pages handed back once written): it
    holds two steps' scans, ~6 bytes an item here (a step of 1 MiB is ~1 byte an item). It
    held ~13 with the kinds and z it returns made in memory (4 bytes an item each: 800 MB
    at 1e8), ~47 before that: every item's hash, z and flag from the scan (17 bytes),
    concatenated (17), then the codes (8) and the columns made from them."""
    per_item = _peak_above_input("looks")
    assert 2 < per_item < 10, per_item


@pytest.mark.slow(seconds=5)  # a build of 1e6 items, in a process of its own
def test_a_sparse_boards_overview_holds_under_150_bytes_an_item_above_its_input():
    """On a board spread 10x wider (~10 items a screen where it had ~1000), nothing merges in
    the finest bands: each holds as many aggregates as items, and the build ~110-117 bytes an
    item (~49 on the board). It was ~175: each run's columns (~40 bytes) were held through
    the band's reduction and tree, the rectangles' columns were sorted in copies, and a
    band's tree copied the aggregates' boxes it was built over; then ~126 (~58 on the board):
    the elements' counts, areas, z and kinds (20 bytes) were held through their sort."""
    per_item = _peak_above_input("overview", spread=10.0)
    assert 40 < per_item < 150, per_item


@pytest.mark.slow(seconds=5)  # a build of 1e6 items, in a process of its own
def test_an_imports_table_joins_its_batches_without_holding_them_twice():
    """Every column, the offsets too, written to files the kernel pages as the batches come,
    then the id index made in files: the ids hashed a step at a time, the hashes and their
    positions sorted a run at a time (``sorted_keys``): ~12 bytes an item at the peak here,
    where a sort in one run holds ~22-28 (the index sorted in memory: 1.2 GB at 1e8 items).
    It was ~50 with the offsets made in memory (8 and 4 bytes, and each batch's lengths, 16,
    till then) and every id's page read at once, 84 with the boxes in memory too, 99 before
    that (~111 at 1e8, traced): every batch's boxes, ids and lengths were held until all
    were joined, and so twice at the join."""
    per_item = _peak_above_input("pack")
    assert 4 < per_item < 17, per_item


@given(order=st.integers(0, 60).flatmap(lambda n: st.permutations(range(n))))
def test_a_gather_in_place_is_a_take(order):
    rows = np.arange(4 * len(order), dtype=np.float64).reshape(-1, 4)
    expected = rows[np.array(order, np.int64)] if order else rows
    gather_in_place(rows, np.array(order, np.int64))
    assert (rows == expected).all()


@settings(max_examples=60, deadline=None)
@given(
    corners=st.lists(
        st.tuples(*[st.sampled_from([-0.0, 0.0, 1.0, -3.5, 7.0, 1e30, -1e30])] * 2, st.integers(0, 3)),
        max_size=40,
    ),
    x_order=st.booleans(),
    coords=st.sampled_from(["float64", "float32"]),
)
@pytest.mark.slow(seconds=30)  # 60 examples, each built in steps of two rows
def test_builds_over_mapped_boxes_a_step_at_a_time_are_the_builds_over_them_in_memory(
    corners, x_order, coords, memory_dir
):
    """The tree and the overview over boxes mapped from a file, read in steps of two rows
    (a step's pages handed back after it), have the same arrays, to the bit, as over the
    same boxes in memory: the signs of zeros, repeated boxes and extremes included. So has
    the tree built to be written, its boxes handed over in runs."""
    boxes = np.array([(x, y, x + w, y + w) for x, y, w in corners], np.float64).reshape(-1, 4)
    path = Path(tempfile.mkdtemp(dir=memory_dir)) / "boxes"  # ~900 scratch files an example
    path.write_bytes(boxes.tobytes())
    with open(path, "rb") as file:
        mapped = (
            np.frombuffer(mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ), np.float64)
            if len(boxes)
            else boxes
        )
    mapped = mapped.reshape(-1, 4)
    kinds, z = np.arange(len(boxes), dtype=np.int32) % 3, np.arange(len(boxes), dtype=np.int32) % 2
    want = QuadTree.bulk_load(boxes, x_order=x_order, coords=coords).to_arrays()
    want_overview = dict(Overview.build_arrays(boxes, kinds, z))
    runs: list[np.ndarray] = []
    with (
        mock.patch("spatial.paging.STEP_BYTES", 64),
        # runs of ~3 boxes, the keys sorted in files four at a time, a band's groups filled two
        # at a time
        MemoryBudget(run_bytes=96, window_bytes=80, sort_bytes=48).held(),
    ):
        got = QuadTree.bulk_load(mapped, x_order=x_order, coords=coords).to_arrays()
        made: list[tuple[int, str]] = []  # what the build keeps in files

        def scratch(length, dtype):
            made.append((length, np.dtype(dtype).str))
            return scratch_array(path.parent, length, dtype)

        got_overview = dict(Overview.build_arrays(mapped, kinds, z, scratch=scratch))
        if coords == "float64":  # as an import writes it: runs of whole leaves of ~3 boxes, its ids in a file
            written = QuadTree.build_arrays(mapped, runs.append, scratch=scratch, x_order=x_order)
            written["boxes"], written["ids"] = (
                np.concatenate([np.empty((0, 4)), *runs]),
                written["ids"].astype(np.int64),
            )
            assert all(written[k].tobytes() == want[k].tobytes() for k in want)
    assert got.keys() == want.keys() and all(got[k].tobytes() == want[k].tobytes() for k in want)
    assert got_overview.keys() == want_overview.keys()
    bands = sorted(int(name.split(".")[0]) for name in got_overview if name.endswith(".count"))
    # The items' first bands first; then, among what each band makes in files (its items,
    # owners, areas...), in order: its aggregates' boxes, counts and z; its tree's boxes
    # (then its keys, order and places), its ids; its slots and parents; then its boxes
    # gathered for the band above (its columns are in files already)
    assert not len(boxes) or made[0] == (len(boxes), np.dtype(np.int16).str)
    at = 1
    f8, i8, i4 = np.dtype(np.float64).str, np.dtype(np.int64).str, np.dtype(np.int32).str
    for band in bands:
        count = len(got_overview[f"{band}.count"])
        for kept in (
            [(4 * count, f8), (count, i4), (count, i4), (4 * count, f8)],
            [(count, i8), (count, i4), (count, i4), (4 * count, f8)],
        ):
            at = next(k for k in range(at, len(made)) if made[k : k + 4] == kept) + 4
    assert all(got_overview[k].tobytes() == want_overview[k].tobytes() for k in want_overview)


def test_a_tree_built_to_be_written_hands_out_runs_of_the_budget_it_is_given():
    """``budget=`` sizes the runs of one build, whatever budget the thread holds; the arrays
    are the same at any budget."""
    boxes, _ = scenes.uniform(2000, seed=1)
    whole: list[np.ndarray] = []
    small: list[np.ndarray] = []
    want = QuadTree.build_arrays(boxes, whole.append)
    with MemoryBudget(run_bytes=32 * 1000).held():  # runs of a thousand boxes: not this build's
        got = QuadTree.build_arrays(boxes, small.append, budget=MemoryBudget(run_bytes=32 * 100))
    assert len(whole) == 1 and len(small) >= 20 and max(map(len, small)) <= 100
    assert np.array_equal(np.concatenate(small), whole[0])
    assert all(np.array_equal(got[k], want[k]) for k in want)


def test_an_overview_built_to_be_written_holds_the_budget_it_is_given_while_it_builds(tmp_path):
    """``budget=`` is what the build's windows read while it runs, whatever the thread holds;
    between the arrays it yields, the caller's own budget is back."""
    from spatial.budget import current

    boxes, _ = scenes.long_document(pages=6, seed=2)
    given, outer = MemoryBudget(window_bytes=80), MemoryBudget(window_bytes=1 << 20)
    seen: list[MemoryBudget] = []

    def scratch(length, dtype):
        seen.append(current())
        return scratch_array(tmp_path, length, dtype)

    with outer.held():
        arrays = Overview.build_arrays(boxes, scratch=scratch, budget=given)
        got = {}
        for name, array in arrays:
            assert current() is outer, f"{name}: the build's budget held past its yield"
            got[name] = array.copy()
    assert seen and all(held is given for held in seen)
    want = dict(Overview.build_arrays(boxes))
    assert got.keys() == want.keys() and all(np.array_equal(got[k], want[k]) for k in want)


def test_a_tree_built_over_boxes_it_owns_is_the_same_tree_over_them():
    """``bulk_load_owned`` puts the boxes in the tree's order where they lie: the same arrays
    as ``bulk_load``'s, the boxes' memory the tree's own."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1e6, 1e6, (20_000, 2))
    boxes = np.hstack([xy, xy + rng.uniform(0, 300, (20_000, 2))])
    expected = QuadTree.bulk_load(boxes).to_arrays()
    owned = boxes.copy()
    tree = QuadTree.bulk_load_owned(owned)
    got = tree.to_arrays()
    assert np.shares_memory(got["boxes"], owned)
    assert all(np.array_equal(got[k], expected[k]) for k in expected)
    assert sorted(tree.query((-1e4, -1e4, 1e4, 1e4)).tolist()) == sorted(
        np.flatnonzero(
            (boxes[:, 0] <= 1e4) & (boxes[:, 2] >= -1e4) & (boxes[:, 1] <= 1e4) & (boxes[:, 3] >= -1e4)
        ).tolist()
    )


@pytest.mark.slow(seconds=10)  # two builds of 1e6 items or more, each in a process
def test_an_items_frames_are_made_holding_a_few_bytes_an_item():
    """The frames of a spilled import's bodies, put in the tree's order: each item's offset in
    that order, its place in that order and the order its bucket's came in are made in files,
    a step at a time, their pages handed back after each. What is held (a bucket of items,
    zstd's contexts, a step) does not grow with the items: the bytes an item are the growth
    from 1e6 items to 2e6, ~1.5 here. Those three held in memory, it was 16.7 (with each
    item's place in int64, 20.9)."""
    one, two = _peak_above_input("frames", items=ITEMS), _peak_above_input("frames", items=2 * ITEMS)
    per_item = 2 * two - one  # (2n * two - n * one) / n
    assert per_item < 5, (one, two)


@pytest.mark.slow(seconds=5)  # a build of 1e6 items, in a process of its own
def test_the_offsets_of_items_in_another_order_hold_a_window_not_all():
    """An import's bodies (and ids) are framed in the tree's order: each position's place in
    it, and the items' offsets in it, are written at random, in files, a window of them a pass
    (``placed``, ``offsets_in``), the offsets read in the order they lie: ~4 bytes an item
    here with windows of 1 MiB, where one window holds ~14 (at 1e8 items, the offsets read at
    random in a step of the order held 730 MB)."""
    per_item = _peak_above_input("offsets")
    assert 1 < per_item < 8, per_item


@pytest.mark.slow(seconds=10)  # two builds of 1e6 items or more, each in a process
def test_a_compactions_fold_of_its_edits_holds_a_few_bytes_an_item():
    """A base's items put back in document order with 1,550 edits folded in (``folded``, what
    a compaction builds from): the order, its inverse, each item's place, the boxes, the ids,
    the bodies and their offsets are made in files, a step or a window held at a time. What
    grows with the items from 1e6 to 2e6 is ~8 bytes an item (a byte each kept, the pages
    the lookups of the edited ids map); the fold in memory held ~150 (a 1e8-item compaction,
    6 GB)."""
    one, two = _peak_above_input("fold", items=ITEMS), _peak_above_input("fold", items=2 * ITEMS)
    per_item = 2 * two - one  # (2n * two - n * one) / n
    assert per_item < 15, (one, two)


def test_an_imports_runs_are_sized_to_what_its_aim_leaves(caplog):
    """``VANTAGE_IMPORT_MEMORY_MB`` sizes an import's runs: half of what the runtime and what
    the build holds whole (~7 bytes an item) leave of it, at most 256 MB; a document needing
    more than the aim still builds, its runs at their least (16 MB), and the log says so."""
    from app.basefile import RUNTIME_BYTES, import_budget
    from app.snapfile import SnapshotFiles
    from spatial.budget import LEAST_RUN_BYTES, MOST_RUN_BYTES

    assert import_budget(10**6, 1400 << 20) == MemoryBudget.of_runs(MOST_RUN_BYTES) == MemoryBudget()
    budget = import_budget(10**8, 1400 << 20)  # (1400 MB - 256 MB - 700 MB) / 2
    assert budget.run_bytes == ((1400 << 20) - RUNTIME_BYTES - 7 * 10**8) // 2 == budget.window_bytes
    assert budget.sort_bytes == budget.run_bytes // 4
    assert not caplog.records
    with caplog.at_level("WARNING", logger="vantage.import"):
        assert SnapshotFiles(Path("unused"), 600 << 20).budget(10**8).run_bytes == LEAST_RUN_BYTES
    assert "past the 600 MB it aims at (VANTAGE_IMPORT_MEMORY_MB)" in caplog.text


def test_a_compactions_fold_holds_its_own_budget_not_the_last_builds(tmp_path, monkeypatch):
    """A compaction's fold is a build in files: its windows are held to the budget of its
    document and ``VANTAGE_IMPORT_MEMORY_MB`` (its ``SnapshotFiles``'), not to whatever budget
    the thread holds (a build of a larger document's, say)."""
    import app.folding
    from app.basefile import RUNTIME_BYTES
    from app.items import Item, batch_of
    from app.registry import Registry
    from app.snapfile import SnapshotFiles
    from app.stores import SQLiteStore
    from spatial.budget import LEAST_RUN_BYTES, current

    n, left = 2000, 100 << 20
    store = SQLiteStore(tmp_path)
    try:
        files = SnapshotFiles(tmp_path / "snapshots", RUNTIME_BYTES + 7 * n + 2 * left)
        doc = Registry(store, files, 1 << 30).create("d")
        doc.import_items([batch_of([Item(f"i{k}", k, 0, k + 1, 1) for k in range(n)], n)])
        doc = Registry(store, files, 1 << 30)[doc.id]  # opened again: mapped from its file
        moved = batch_of([Item("i5", 50, 50, 60, 60)], 1)
        doc.edit(list(zip(moved.ids, map(tuple, moved.boxes.tolist()), moved.bodies, strict=True)))
        seen, windows = [], app.folding.windows

        def watched(rows: int, row_bytes: int, in_file: bool):
            seen.append(current().window_bytes)
            return windows(rows, row_bytes, in_file)

        monkeypatch.setattr(app.folding, "windows", watched)
        with MemoryBudget.of_runs(LEAST_RUN_BYTES).held():  # as a larger document's build holds
            doc.compact()
    finally:
        store.close()
    assert seen == [left], seen
