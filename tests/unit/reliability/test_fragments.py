"""Split and bounded reassembly of large samples (``arpz.core.protocol.fragments``), pure."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arpz.core.protocol.fragments import (
    HEADER,
    HEADER_BYTES,
    FragmentError,
    Reassembler,
    fragment_count,
    parse,
    split,
)


def frame(n: int, seed: int = 0) -> bytes:
    return random.Random(seed).randbytes(n)


def test_split_cuts_a_frame_into_fragments_of_the_size_asked_and_back() -> None:
    payload = frame(921_600)
    frags = list(split(7, payload, 1280))
    assert len(frags) == fragment_count(921_600, 1280) == 720
    assert {len(f) for f in frags} == {HEADER_BYTES + 1280}
    r = Reassembler()
    done = [r.add("w", f, stamp_ns=5) for f in frags]
    assert done[:-1] == [None] * 719
    last = done[-1]
    assert last is not None and last.payload == payload and last.frame_id == 7
    assert (last.fragments, last.stamp_ns, last.source) == (720, 5, "w")
    s = r.stats()
    assert (s.frames_delivered, s.bytes_delivered, s.in_assembly, s.assembly_bytes) == (
        1,
        921_600,
        0,
        0,
    )


def test_the_last_fragment_is_short_and_an_empty_frame_is_one_empty_fragment() -> None:
    frags = list(split(1, b"x" * 2561, 1280))
    assert [len(f) - HEADER_BYTES for f in frags] == [1280, 1280, 1]
    (empty,) = split(1, b"", 1280)
    done = Reassembler().add("w", empty)
    assert done is not None and done.payload == b""


@settings(max_examples=60, deadline=None)
@given(
    size=st.integers(0, 20_000),
    chunk=st.integers(1, 3000),
    seed=st.integers(0, 2**32),
)
def test_any_order_with_duplicates_reassembles_exactly_once(
    size: int, chunk: int, seed: int
) -> None:
    rng = random.Random(seed)
    payload = frame(size, seed)
    frags = list(split(3, payload, chunk))
    order = frags + rng.sample(frags, k=min(len(frags), 5))  # duplicates, some after completion
    rng.shuffle(order)
    r = Reassembler()
    done = [c for c in (r.add("w", f) for f in order) if c is not None]
    assert len(done) == 1 and done[0].payload == payload
    s = r.stats()
    assert s.fragments_received == len(order)
    assert s.fragments_duplicate + s.fragments_stale == len(order) - len(frags)
    assert s.in_assembly == 0


@settings(max_examples=60, deadline=None)
@given(
    frames=st.integers(2, 12),
    loss=st.floats(0.0, 0.3),
    seed=st.integers(0, 2**32),
    in_order=st.booleans(),
)
def test_every_frame_is_delivered_dropped_or_missing_and_the_newest_wins(
    frames: int, loss: float, seed: int, in_order: bool
) -> None:
    """Fragments of consecutive frames in order with losses (the reliable channel's KEEP_LAST):
    frames sent == delivered + dropped incomplete + missing + still in assembly, and a frame is
    never delivered after a newer one."""
    rng = random.Random(seed)
    payloads = [frame(rng.randint(0, 6000), seed + i) for i in range(frames)]
    r = Reassembler(in_order=in_order, max_frames=frames + 1)
    delivered: list[int] = []
    first = True
    for i, p in enumerate(payloads, start=1):
        for f in split(i, p, 700):
            if not first and rng.random() < loss:
                continue
            first = False  # the reader's first fragment is from frame 1
            done = r.add("w", f)
            if done is not None:
                assert done.payload == payloads[done.frame_id - 1]
                delivered.append(done.frame_id)
    assert delivered == sorted(delivered)
    s = r.stats()
    assert s.frames_delivered == len(delivered)
    # frames after the last delivered one that lost every fragment are unknown to the reassembler
    seen_after_last = frames - (delivered[-1] if delivered else 0)
    assert (
        s.frames_delivered + s.frames_dropped_incomplete + s.frames_missing + s.in_assembly
        <= frames
        <= s.frames_delivered + s.frames_dropped_incomplete + s.frames_missing + seen_after_last
    )
    if in_order:
        assert s.in_assembly <= 1
    if loss == 0.0:
        assert delivered == list(range(1, frames + 1))


def test_an_older_incomplete_frame_is_dropped_and_counted_when_a_newer_one_completes() -> None:
    r = Reassembler()
    one, two = list(split(1, frame(3000), 1000)), list(split(2, frame(3000, 1), 1000))
    assert r.add("w", one[0]) is None and r.add("w", one[1]) is None
    assert r.stats().in_assembly == 1
    done = [r.add("w", f) for f in two]
    assert done[-1] is not None and done[-1].frame_id == 2
    assert r.add("w", one[2]) is None  # frame 1 would complete now, but frame 2 won
    s = r.stats()
    assert (s.frames_delivered, s.frames_dropped_incomplete, s.fragments_stale) == (1, 1, 1)
    assert (s.in_assembly, s.assembly_bytes) == (0, 0)


def test_in_order_drops_the_older_frame_as_soon_as_a_newer_one_begins() -> None:
    r = Reassembler(in_order=True)
    r.add("w", next(split(1, frame(3000), 1000)))
    r.add("w", next(split(4, frame(3000), 1000)))  # frames 2 and 3 never showed a fragment
    s = r.stats()
    assert (s.frames_dropped_incomplete, s.frames_missing, s.in_assembly) == (1, 2, 1)


def test_sources_are_reassembled_apart() -> None:
    r = Reassembler(in_order=True)
    a, b = list(split(1, frame(2000), 1000)), list(split(1, frame(2000, 1), 1000))
    assert r.add("a", a[0]) is None and r.add("b", b[0]) is None
    done_a, done_b = r.add("a", a[1]), r.add("b", b[1])
    assert done_a is not None and done_b is not None
    assert (done_a.source, done_b.source) == ("a", "b") and done_a.payload != done_b.payload


def test_memory_is_bounded_and_what_exceeds_the_bounds_is_counted() -> None:
    r = Reassembler(max_frames=2, max_bytes=10_000, max_frame_bytes=8_000)
    for fid in (1, 2, 3):  # three frames begin: the oldest is evicted
        r.add("w", next(split(fid, frame(3000), 1000)))
    s = r.stats()
    assert (s.in_assembly, s.frames_dropped_over_limit, s.assembly_bytes) == (2, 1, 6000)
    r.add("w", list(split(1, frame(3000), 1000))[1])  # a late fragment of the evicted frame
    assert r.stats().fragments_stale == 1
    r.add("w", next(split(4, frame(6000), 1000)))  # 6000 more bytes: frame 2 must go too
    s = r.stats()
    assert (s.in_assembly, s.frames_dropped_over_limit, s.assembly_bytes) == (2, 2, 9000)
    r.add("w", next(split(5, frame(9000), 1000)))  # larger than max_frame_bytes: refused
    s = r.stats()
    assert (s.frames_too_large, s.in_assembly, s.assembly_bytes) == (1, 2, 9000)
    # completing frame 4 settles 1..3 (1 and 2 evicted, 3 incomplete) and frame 5 stays refused
    for f in list(split(4, frame(6000), 1000))[1:]:
        r.add("w", f)
    s = r.stats()
    assert (s.frames_delivered, s.frames_dropped_incomplete, s.frames_missing) == (1, 1, 0)
    assert (s.in_assembly, s.assembly_bytes) == (0, 0)


def test_the_number_of_sources_is_bounded() -> None:
    r = Reassembler(max_sources=2)
    for source in ("a", "b", "c"):
        r.add(source, next(split(1, frame(2000), 1000)))
    s = r.stats()
    assert s.in_assembly == 2 and s.frames_dropped_incomplete == 1  # "a" was forgotten


@pytest.mark.parametrize(
    "bad",
    [
        b"short",
        HEADER.pack(2, 1, 0, 1, 3, 3) + b"abc",  # version
        HEADER.pack(1, 0, 0, 1, 3, 3) + b"abc",  # frame id 0
        HEADER.pack(1, 1, 0, 2, 3, 3) + b"abc",  # count disagrees with total / chunk
        HEADER.pack(1, 1, 1, 1, 3, 3) + b"abc",  # index beyond count
        HEADER.pack(1, 1, 0, 1, 3, 3) + b"ab",  # length disagrees with the header
        HEADER.pack(1, 1, 0, 1, 3, 0) + b"abc",  # chunk 0
    ],
)
def test_malformed_fragments_are_refused_and_counted(bad: bytes) -> None:
    assert parse(bad) is None
    r = Reassembler()
    assert r.add("w", bad) is None and r.stats().bad_fragments == 1


def test_a_fragment_that_disagrees_with_its_frame_is_refused() -> None:
    r = Reassembler()
    r.add("w", next(split(1, frame(3000), 1000)))
    r.add("w", list(split(1, frame(4000), 1000))[1])  # same frame id, another total
    s = r.stats()
    assert s.bad_fragments == 1 and s.in_assembly == 1


def test_split_refuses_what_the_header_cannot_describe() -> None:
    with pytest.raises(FragmentError, match="fragment_bytes"):
        list(split(1, b"x", 0))
    with pytest.raises(FragmentError, match="frame id"):
        list(split(0, b"x", 10))
    with pytest.raises(FragmentError, match="max_frames"):
        Reassembler(max_frames=0)
