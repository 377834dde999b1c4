"""The packed byte strings every answer is joined from, against plain Python's join."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from app.table import Packed

parts_and_picks = st.lists(st.binary(max_size=40), max_size=30).flatmap(
    lambda parts: st.tuples(
        st.just(parts),
        st.lists(st.integers(0, len(parts) - 1), max_size=60) if parts else st.just([]),
        st.sampled_from([b",", b"\n"]),
        st.tuples(st.binary(max_size=8), st.binary(max_size=8)),
    )
)


@given(parts_and_picks)
def test_join_is_pythons_join_of_the_picked_parts_between_the_ends(case):
    parts, picks, sep, (head, tail) = case
    packed = Packed.of(parts)
    joined = head + sep.join(parts[p] for p in picks) + tail
    assert packed.join(np.array(picks, np.int64), sep, (head, tail)) == joined


@given(
    st.lists(st.lists(st.tuples(st.binary(max_size=20), st.booleans()), max_size=20), min_size=1, max_size=4)
)
def test_gather_keeps_the_masked_parts_in_order(packs):
    gathered = Packed.gather(
        [Packed.of([part for part, _ in pack]) for pack in packs],
        [np.array([keep for _, keep in pack], bool) for pack in packs],
    )
    kept = [part for pack in packs for part, keep in pack if keep]
    assert [gathered[i] for i in range(len(gathered))] == kept
