"""Bodies compressed a frame at a time read back as the packed bodies they were made from:
item by item, joined, taken and decompressed whole, whatever the frames' size and the cache's."""

import ctypes
import mmap
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app import frames
from app.frames import DecodedFrames, Framed, framed_arrays
from app.packed import Packed, Spill

pytestmark = pytest.mark.usefixtures("scratch_in_files")  # small inputs, mapped paths

BODIES = st.lists(st.binary(min_size=0, max_size=300), min_size=1, max_size=120)


@settings(max_examples=150, deadline=None)
@given(
    bodies=BODIES,
    data=st.data(),
    frame_bytes=st.sampled_from([1, 64, 700, 1 << 14]),
    bucket_bytes=st.sampled_from([1, 300, 5000, 1 << 24]),
    cache_bytes=st.sampled_from([0, 500, 1 << 24]),
    spill=st.booleans(),
)
def test_framed_bodies_read_as_the_packed_ones(
    bodies, data, frame_bytes, bucket_bytes, cache_bytes, spill, tmp_path_factory
):
    """With ``spill``, bodies spilled to a file are framed in two passes through buckets."""
    n = len(bodies)
    order = np.array(data.draw(st.permutations(range(n))), np.int64)
    packed = Packed.of(bodies)
    expected = packed.take(order)  # the items at ``order``: what the frames must read as
    directory = tmp_path_factory.mktemp("frames") if spill else None
    if directory is not None:
        with Spill(directory) as file:
            file.write(packed.buffer)
            packed = Packed(file.mapped(), packed.offsets)
    old = frames.FRAME_BYTES, frames.BUCKET_BYTES, frames.PASS_BYTES
    frames.FRAME_BYTES, frames.BUCKET_BYTES, frames.PASS_BYTES = frame_bytes, bucket_bytes, bucket_bytes * 3
    decoded = DecodedFrames(cache_bytes)
    try:
        arrays = framed_arrays(packed, order, directory)
        framed = Framed(arrays["frames"], arrays["at"], arrays["first"], arrays["offsets"], decoded=decoded)
        assert len(framed) == n and np.array_equal(framed.offsets, expected.offsets)
        assert len(arrays["first"]) - 1 <= n and arrays["first"][-1] == n
        for i in data.draw(st.lists(st.integers(0, n - 1), max_size=20)):
            assert framed[i] == bytes(expected[i])
        positions = np.array(data.draw(st.lists(st.integers(0, n - 1), max_size=60)), np.int64)
        sep, ends = data.draw(st.sampled_from([(b",", (b"[", b"]")), (b"\n", (b"", b"\n"))]))
        assert framed.join(positions, sep, ends) == expected.join(positions, sep, ends)
        assert decoded.bytes <= cache_bytes
        whole = framed.unpacked(directory)
        assert bytes(whole.buffer) == bytes(expected.buffer)
        again = np.array(data.draw(st.permutations(range(n))), np.int64)
        again = again[: data.draw(st.integers(0, n))]  # some of them, as a compaction's deletions leave
        taken = framed.take(again, directory)  # through buckets, with ``directory``
        assert bytes(taken.buffer) == bytes(expected.take(again).buffer)
        assert np.array_equal(taken.offsets, expected.take(again).offsets)
        if directory is not None:  # the packed ones (an import's ids) the same way, their places given
            places = np.empty(n, np.int64)
            places[order] = np.arange(n)
            taken = frames.taken(packed, order, directory, places)
            assert bytes(taken.buffer) == bytes(expected.buffer)
            assert np.array_equal(taken.offsets, expected.offsets)
    finally:
        frames.FRAME_BYTES, frames.BUCKET_BYTES, frames.PASS_BYTES = old


def _framed(frames_count: int, decoded: DecodedFrames, seed: int = 1) -> tuple[Framed, Packed]:
    """About ``frames_count`` frames of items of 50-400 bytes, decoded through ``decoded``;
    and the packed items they read as."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(50, 400, frames_count * frames.FRAME_BYTES // 225)
    packed = Packed.of([bytes(rng.integers(97, 123, int(n), np.uint8)) for n in sizes])
    arrays = framed_arrays(packed, np.arange(len(packed)))
    return Framed(arrays["frames"], arrays["at"], arrays["first"], arrays["offsets"], decoded=decoded), packed


def _resident(array: np.ndarray) -> int:
    """Bytes of the pages under ``array`` in memory (mincore(2))."""
    page = mmap.PAGESIZE
    start = array.ctypes.data // page * page
    length = array.ctypes.data + array.nbytes - start
    pages = (ctypes.c_ubyte * -(-length // page))()
    assert ctypes.CDLL(None).mincore(ctypes.c_void_p(start), ctypes.c_size_t(length), pages) == 0
    return sum(b & 1 for b in pages) * page


def test_decoded_frames_hold_the_memory_of_the_limit_whatever_is_read():
    """Frames let go hand their pages back: a pass over every frame of a document through a
    cache of eight holds about eight frames' memory, not the document's."""
    limit = 8 * frames.FRAME_BYTES
    framed, packed = _framed(200, DecodedFrames(limit))
    rng = np.random.default_rng(2)
    for _ in range(400):
        positions = rng.integers(0, len(packed), 20)
        assert framed.join(positions, b",", (b"[", b"]")) == packed.join(positions, b",", (b"[", b"]"))
    assert framed.decoded.bytes <= limit
    held = framed.present.astype(bool).sum()
    assert _resident(framed._arena) <= limit + 2 * held * mmap.PAGESIZE, "pages of frames let go still held"


def test_frames_smaller_than_a_page_let_go_leave_the_others_in_it_whole(monkeypatch):
    """A page may hold several small frames: one let go hands the page back only when no
    frame in it is kept, so those kept read as they were."""
    monkeypatch.setattr(frames, "FRAME_BYTES", 64)
    rng = np.random.default_rng(3)
    packed = Packed.of([bytes(rng.integers(97, 123, int(n), np.uint8)) for n in rng.integers(1, 60, 3000)])
    arrays = framed_arrays(packed, np.arange(len(packed)))
    framed = Framed(
        arrays["frames"], arrays["at"], arrays["first"], arrays["offsets"], decoded=DecodedFrames(2000)
    )
    for _ in range(5000):
        positions = rng.integers(0, len(packed), int(rng.integers(1, 6)))
        assert framed.join(positions) == packed.join(positions)


def test_a_frame_read_again_and_again_stays_while_others_come_and_go(monkeypatch):
    """The frames read least lately go first: one read at every step is decoded once, while
    each other is let go as the limit needs."""
    framed, packed = _framed(60, DecodedFrames(4 * frames.FRAME_BYTES))
    decoded: list[int] = []
    decode = framed._decode
    monkeypatch.setattr(framed, "_decode", lambda f: decoded.append(f) or decode(f))
    first = framed.first
    for f in range(1, len(first) - 1):
        positions = np.array([0, first[f]], np.int64)
        assert framed.join(positions) == packed.join(positions)
    assert decoded.count(0) == 1 and sorted(decoded) == list(range(len(first) - 1))
    assert framed.present.astype(bool).sum() <= 4


def test_documents_sharing_a_small_cache_read_their_own_items_from_many_threads():
    """A frame is let go only when no join is reading it: threads joining two documents'
    items through one small cache each get exactly their items."""
    decoded = DecodedFrames(3 * frames.FRAME_BYTES)
    documents = [_framed(40, decoded, seed) for seed in (1, 2)]
    wrong: list[str] = []

    def pan(seed: int) -> None:
        rng = np.random.default_rng(seed)
        for step in range(300):
            framed, packed = documents[(seed + step) % 2]
            positions = rng.integers(0, len(packed), int(rng.integers(1, 40)))
            if framed.join(positions) != packed.join(positions):
                wrong.append(f"thread {seed}, step {step}")

    threads = [threading.Thread(target=pan, args=(seed,)) for seed in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not wrong, wrong[:5]
    assert decoded.bytes <= decoded.limit


def test_a_frame_holds_at_most_frame_bytes_unless_one_item_is_bigger(monkeypatch):
    monkeypatch.setattr(frames, "FRAME_BYTES", 1000)
    bodies = [b"x" * 100] * 50 + [b"y" * 5000] + [b"z" * 100] * 50
    arrays = framed_arrays(Packed.of(bodies), np.arange(len(bodies)))
    sizes = np.diff(arrays["offsets"][arrays["first"]])
    assert sorted(set(sizes.tolist())) == [1000, 5000] and len(sizes) == 11
    assert len(arrays["frames"]) < sum(map(len, bodies)) // 10  # compressed


def test_the_buckets_room_on_the_disk_goes_as_each_is_read_back(tmp_path, monkeypatch):
    """Items put in another order go through a scratch file of buckets, as large as the items
    (~11 GB at 1e8): each bucket's room on the disk is freed once it is read back, so the file
    is empty when the last is, while the snapshot file grows. Each punch is watched: the
    file's allocated bytes once it is done."""
    import os

    rng = np.random.default_rng(3)
    bodies = [bytes(rng.integers(65, 90, int(rng.integers(50, 400)), dtype=np.uint8)) for _ in range(20_000)]
    with Spill(tmp_path) as file:
        file.write(Packed.of(bodies).buffer)
        packed = Packed(file.mapped(), Packed.of(bodies).offsets)
    order = rng.permutation(len(bodies)).astype(np.int64)
    monkeypatch.setattr(frames, "BUCKET_BYTES", 1 << 16)
    monkeypatch.setattr(frames, "PASS_BYTES", 1 << 16)
    allocated, punch = [], frames.punch

    def watched(fd: int, offset: int, length: int) -> None:
        punch(fd, offset, length)
        allocated.append(os.fstat(fd).st_blocks * 512)

    monkeypatch.setattr(frames, "punch", watched)
    taken = frames.taken(packed, order, tmp_path)
    total = sum(map(len, bodies))
    assert len(allocated) > 10, len(allocated)  # a punch a bucket
    assert max(allocated[: len(allocated) // 4]) > total / 2  # the first buckets' read: most are there
    assert allocated[-1] < total / 20, (allocated[-1], total)  # the last one's: none is left
    assert [bytes(taken[k]) for k in range(0, len(bodies), 997)] == [bodies[p] for p in order[::997].tolist()]


@settings(max_examples=200, deadline=None)
@given(
    sizes=st.lists(st.integers(1, 40), min_size=1, max_size=600),
    data=st.data(),
)
def test_each_item_is_located_in_its_frame_as_a_search_finds_it(sizes, data):
    """Items spread over a few frames or many more frames than items (the two ways
    ``_located`` numbers them), and items past the last frame, which it must not confirm."""
    first = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    n = int(first[-1])
    positions = np.array(data.draw(st.lists(st.integers(0, n + 2), max_size=300)), np.int64)
    frames_of, confirmed = frames._located(first, positions)
    frame_of = np.searchsorted(first, positions, side="right") - 1
    assert np.array_equal(frames_of, np.unique(frame_of))
    assert confirmed == bool((positions < n).all())
