"""Writer and Reader over the in-memory transport: threads, blocking write, events, close."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import msgspec
import pytest

from arpz.channel import (
    QOS_RELIABLE_ALL,
    DataInfo,
    HistoryFullError,
    HistoryPolicy,
    QosProfile,
    Reader,
    ReaderEventCallbacks,
    ReliabilityPolicy,
    Writer,
    WriterEventCallbacks,
)
from arpz.channel._channel import _heartbeat_at, _Turns, tick_intervals_s
from arpz.core.protocol import wire
from arpz.core.protocol._common import new_guid
from arpz.core.protocol.reader_machine import ReaderMachine
from arpz.core.protocol.timers import FakeClock
from arpz.core.protocol.writer_machine import WriterMachine
from arpz.core.transport import TransportError
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import SlowFirstDelivery, wait_until


def test_samples_flow_in_order_and_callbacks_run_on_the_worker_thread() -> None:
    got: list[tuple[bytes, DataInfo]] = []
    threads: set[str] = set()

    def on_data(payload: bytes, info: DataInfo) -> None:
        threads.add(threading.current_thread().name)
        got.append((payload, info))

    with _pair("f/robot/*/sensor/*", "f/robot/r1/sensor/lidar", QOS_RELIABLE_ALL, on_data) as (
        reader,
        writer,
    ):
        seqs = [writer.write(b"%d" % i) for i in range(200)]
        assert seqs == list(range(1, 201))
        wait_until(lambda: len(got) == 200, what="all samples")
        assert [info.seq for _, info in got] == seqs
        assert got[0][1].key == "f/robot/r1/sensor/lidar" and got[0][1].writer == writer.guid
        assert threads == {"arpz-reader-f/robot/*/sensor/*"}
        assert writer.wait_for_acknowledgments(2.0)
        assert reader.stats().delivered == 200 and writer.stats().sent == 200


def test_keep_all_write_blocks_then_raises_a_clear_error_when_no_one_acknowledges() -> None:
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=5, max_blocking_time_s=0.2)
    # A reader that matched and then went silent (its token is there, no ACKNACK ever comes).
    b.declare_token(wire.reader_token("t", "ab" * 8, "RVA_0_0"))
    writer = Writer(a, "t", qos)
    try:
        wait_until(lambda: writer.matched_count == 1, what="match")
        t0 = time.monotonic()
        with pytest.raises(HistoryFullError, match="abababababababab"):
            for i in range(10):
                writer.write(b"%d" % i)
        assert time.monotonic() - t0 >= 0.2
        assert writer.stats().sent == 5
    finally:
        writer.close()
        a.close()
        b.close()


def test_incompatible_qos_events_reach_both_sides() -> None:
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    seen: list[str] = []
    events_w = WriterEventCallbacks(
        incompatible_qos=lambda s: seen.append("w:" + s.last_policy_kind.value)
    )
    events_r = ReaderEventCallbacks(
        incompatible_qos=lambda s: seen.append("r:" + s.last_policy_kind.value)
    )
    be = QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT)
    with (
        Writer(a, "t", be, events=events_w),
        Reader(b, "t", QosProfile(), lambda p, i: None, events=events_r) as reader,
    ):
        wait_until(lambda: len(seen) == 2, what="both events")
        assert sorted(seen) == ["r:reliability", "w:reliability"]
        assert reader.matched_count == 0
    a.close()
    b.close()


class _nullctx:
    def __init__(self, t: MemoryTransport) -> None:
        self.t = t

    def __enter__(self) -> MemoryTransport:
        return self.t

    def __exit__(self, *exc: object) -> None:
        self.t.close()


@contextlib.contextmanager
def _pair(
    reader_key: str,
    writer_key: str,
    qos: QosProfile,
    on_data: Callable[[bytes, DataInfo], None],
    *,
    synced: bool = True,
) -> Iterator[tuple[Reader, Writer]]:
    """A Reader and a Writer on two in-memory transports of one bus, matched (and, ``synced``,
    with the writer's SYNC acknowledged, so its first write is not held back)."""
    bus = MemoryBus()
    with (
        _nullctx(MemoryTransport(bus)) as a,
        _nullctx(MemoryTransport(bus)) as b,
        Reader(b, reader_key, qos, on_data) as reader,
        Writer(a, writer_key, qos) as writer,
    ):
        wait_until(lambda: writer.matched_count == 1 and reader.matched_count == 1, what="match")
        if synced:
            wait_until(lambda: writer.wait_for_acknowledgments(0.01), what="sync")
        yield reader, writer


def test_a_double_wildcard_reader_gets_data_but_never_control_traffic() -> None:
    bus = MemoryBus()
    got: list[tuple[bytes, str]] = []
    with (
        _nullctx(MemoryTransport(bus)) as a,
        _nullctx(MemoryTransport(bus)) as b,
        Reader(b, "arpz/**", QOS_RELIABLE_ALL, lambda p, i: got.append((p, i.key))) as reader,
        Writer(a, "arpz/f/robot/r1/sensor/x", QOS_RELIABLE_ALL) as writer,
    ):
        wait_until(lambda: writer.matched_count == 1, what="match")
        wait_until(lambda: writer.wait_for_acknowledgments(0.01), what="sync")
        for i in range(50):
            writer.write(b"%d" % i)
        wait_until(lambda: len(got) == 50, what="50 samples")
        assert {k for _, k in got} == {"arpz/f/robot/r1/sensor/x"}
        assert [p for p, _ in got] == [b"%d" % i for i in range(50)]
        assert reader.stats().bad_input == 0


def test_turns_run_in_ticket_order_one_at_a_time_whatever_order_threads_arrive_in() -> None:
    turns = _Turns()
    tickets = [turns.take() for _ in range(6)]
    ran: list[int] = []
    running = [0]
    overlap = [False]

    def perform(actions: list[object]) -> None:
        running[0] += 1
        overlap[0] |= running[0] > 1
        time.sleep(0.005)
        ran.append(len(actions))
        running[0] -= 1

    threads = [
        threading.Thread(target=turns.run, args=(t, perform, [None] * t))
        for t in reversed(tickets)  # the last ticket's thread starts first
    ]
    for thread in threads:
        thread.start()
        time.sleep(0.002)
    for thread in threads:
        thread.join(5.0)
    assert ran == tickets and not overlap[0]


def test_a_turn_whose_perform_raises_still_passes_on() -> None:
    turns = _Turns()
    first, second = turns.take(), turns.take()

    def boom(actions: list[object]) -> None:
        raise RuntimeError("callback bug")

    with pytest.raises(RuntimeError):
        turns.run(first, boom, [])
    done: list[int] = []
    turns.run(second, lambda actions: done.append(1), [])
    assert done == [1]


def test_events_run_on_the_control_thread_and_close_ends_both_threads() -> None:
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    event_threads: set[str] = set()
    events = ReaderEventCallbacks(
        matched=lambda s: event_threads.add(threading.current_thread().name)
    )
    reader = Reader(b, "t/x", QOS_RELIABLE_ALL, lambda p, i: None, events=events)
    with Writer(a, "t/x", QOS_RELIABLE_ALL):
        wait_until(lambda: bool(event_threads), what="matched event")
    assert event_threads == {"arpz-reader-t/x/control"}
    names = {"arpz-reader-t/x", "arpz-reader-t/x/control"}
    assert names <= {t.name for t in threading.enumerate()}
    t0 = time.monotonic()
    reader.close()  # the delivery thread is blocked in its FIFO's recv: undeclare ends it
    assert time.monotonic() - t0 < 1.0
    assert not names & {t.name for t in threading.enumerate()}
    a.close()
    b.close()


def test_a_gap_seen_by_the_delivery_thread_wakes_the_idle_control_thread_to_nack_it() -> None:
    """The NACK is due within nack_delay_s (2 ms); the control thread sleeps up to 50 ms when
    nothing is pending, so the delivery thread must wake it (without, a 10 %-loss link had a
    median latency of 14 ms instead of 0.2)."""
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    with (
        Reader(b, "t/x", QOS_RELIABLE_ALL, lambda p, i: None) as reader,
        Writer(a, "t/x", QOS_RELIABLE_ALL) as writer,
    ):
        wait_until(lambda: writer.matched_count == 1 and reader.matched_count == 1, what="match")
        wait_until(lambda: writer.wait_for_acknowledgments(0.01), what="sync")
        writer.write(b"1")
        wait_until(lambda: reader.stats().delivered == 1, what="first sample")
        wakes: list[int] = []
        channel = reader._channel
        woken = channel.wake
        channel.wake = lambda: (wakes.append(1), woken())[1]  # type: ignore[method-assign]
        guid = bytes.fromhex(writer.guid)
        a.put("t/x", b"3", attachment=wire.encode_data(0, guid, 3, time.time_ns()))  # 2 missing
        wait_until(lambda: bool(wakes), what="the control thread woken")
        wait_until(lambda: reader.stats().nacks >= 1, what="the gap NACKed")
    a.close()
    b.close()


class _BrokenPull:
    """A pull subscriber whose receive fails at once, as a closed session's does."""

    def try_recv(self) -> None:
        return None

    def recv(self) -> tuple[str, bytes, bytes | None]:
        raise TransportError("session closed under the reader")

    def waited_ns(self) -> None:
        return None

    def undeclare(self) -> None:
        pass


class _TransportWithBrokenPull(MemoryTransport):
    def subscribe_pull(self, key_expr: str, capacity: int) -> _BrokenPull:  # type: ignore[override]
        return _BrokenPull()


def test_a_delivery_thread_that_cannot_receive_says_so_and_counts_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Not a silent stop: the reader would never deliver again."""
    transport = _TransportWithBrokenPull(MemoryBus())
    with (
        caplog.at_level(logging.ERROR, logger="arpz.channel"),
        Reader(transport, "t/x", QOS_RELIABLE_ALL, lambda p, i: None) as reader,
    ):
        wait_until(
            lambda: reader.stats().callback_errors == 1 and "delivery stopped" in caplog.text,
            what="the failure counted and logged",
        )
    caplog.clear()
    with caplog.at_level(logging.ERROR, logger="arpz.channel"):  # a normal close: quiet
        bus = MemoryBus()
        with Reader(MemoryTransport(bus), "t/x", QOS_RELIABLE_ALL, lambda p, i: None):
            time.sleep(0.05)
    assert "delivery stopped" not in caplog.text


def test_a_readers_delivery_idle_time_counts_its_waits_and_not_its_work() -> None:
    """What the CEDDP's overload governor reads: a reader waiting for data is idle, the wait in
    progress included; a slow on_data is work, not idleness."""
    done: list[bytes] = []

    def slow(payload: bytes, info: DataInfo) -> None:
        time.sleep(0.3)  # deliberately: on_data's own time is the delivery thread's work
        done.append(payload)

    with _pair(
        "f/robot/*/sensor/*", "f/robot/r1/sensor/lidar", QOS_RELIABLE_ALL, slow, synced=False
    ) as (reader, writer):
        start, idle0 = time.perf_counter(), reader.delivery_idle_s
        time.sleep(0.3)  # deliberately: nothing is written, the reader waits the whole time
        assert reader.delivery_idle_s - idle0 == pytest.approx(
            time.perf_counter() - start, abs=0.05
        )
        busy_from, idle1 = time.perf_counter(), reader.delivery_idle_s
        writer.write(b"one")  # a lone sample: the delivery thread takes it from its FIFO
        wait_until(lambda: len(done) == 1, what="one slow delivery")
        elapsed = time.perf_counter() - busy_from
        assert elapsed >= 0.3
        assert reader.delivery_idle_s - idle1 < elapsed - 0.25


def test_a_writer_ticks_at_its_batch_delay_or_sync_period_not_at_the_reader_s_nack_delay() -> None:
    """nack_delay_s is how long a reader waits before it NACKs: a writer has no use for it. A
    streaming bulk writer (20 ms batches) ticked at it, ten times a batch."""
    qos = QosProfile(nack_delay_s=0.002, nack_period_s=0.02, batch_max_delay_s=0.02)
    writer = WriterMachine("t/a", qos, new_guid(), FakeClock())
    reader = ReaderMachine("t/a", qos, new_guid(), FakeClock())
    assert tick_intervals_s(writer)[0] == 0.02
    assert tick_intervals_s(reader)[0] == 0.002
    quick = QosProfile(nack_delay_s=0.002, nack_period_s=0.02, batch_max_delay_s=0.0005)
    assert tick_intervals_s(WriterMachine("t/a", quick, new_guid(), FakeClock()))[0] == 0.0005


class _PreemptedClock:
    """The real monotonic clock, read by a thread that then loses the CPU for 5 ms."""

    def monotonic_s(self) -> float:
        now = time.monotonic()
        time.sleep(0.005)  # deliberately: the reading thread waits for the GIL
        return now

    def wall_ns(self) -> int:
        return time.time_ns()


def test_a_writer_s_worker_never_aims_before_its_heartbeat_is_due() -> None:
    """The worker sleeps until the writer's next heartbeat; aimed a little early, it woke to
    find nothing due and woke again at once (a quiet writer ticked twice 0.2 ms apart in CI).
    The machine's clock and the worker's may be read with a pause between them."""
    writer = WriterMachine("t/a", QosProfile(heartbeat_period_s=0.2), new_guid(), _PreemptedClock())
    writer.tick()  # arms the timer a period from now, in the machine's clock
    for _ in range(5):
        assert _heartbeat_at(writer) >= writer.next_heartbeat_s


def count_ticks(writer: Writer) -> list[float]:
    """The times of the writer's worker's ticks from now on (appended as they happen)."""
    machine = writer._machine
    ticks: list[float] = []
    tick = machine.tick

    def counting(backlog: int = 0) -> list[Any]:
        ticks.append(time.monotonic())
        return tick(backlog)

    with writer._channel.lock:
        machine.tick = counting  # type: ignore[method-assign]
    return ticks


def test_an_idle_writer_sleeps_and_heartbeats_at_its_period_once_it_writes() -> None:
    """A CEDDP keeps a Hello writer per robot: idle, each woke 20 times a second (a 50 ms cap
    on its worker's sleep), then once a heartbeat period (10 times a second, each a turn of the
    GIL). With nothing written and nothing to say its timer now sleeps up to a second; a write
    re-arms it, and heartbeats go out at their period while a reader misses something."""
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    qos = QosProfile(heartbeat_period_s=0.2)
    writer = Writer(a, "t/idle", qos)
    machine = writer._machine
    ticks = count_ticks(writer)
    try:
        time.sleep(1.5)  # deliberately: the wakes of an idle 1.5 s (the first may precede it)
        assert 1 <= len(ticks) <= 2, ticks  # 7 at one a heartbeat period, 30 with the cap
        assert machine.quiet
        # a reader that matched and never acknowledges: heartbeats every period
        b.declare_token(wire.reader_token("t/idle", "ab" * 8, "RVA_0_0"))
        wait_until(lambda: writer.matched_count == 1, what="match")
        writer.write(b"x")
        before = machine.heartbeats
        time.sleep(1.0)  # deliberately: the heartbeats of a second
        assert 3 <= machine.heartbeats - before <= 7
    finally:
        writer.close()
        a.close()
        b.close()


def test_an_idle_reader_sleeps_until_something_is_pending() -> None:
    """A robot keeps four readers (commands, configuration, QoS, Hello): idle, each woke 20
    times a second, and 50 idle robots (8 topics at 1 Hz) saturated two cores. It now wakes
    about once a second, or at a tenth of a requested deadline; a gap still gets its NACK at
    once (test_a_gap_seen_by_the_delivery_thread_wakes_the_idle_control_thread_to_nack_it)."""
    assert tick_intervals_s(ReaderMachine("t/a", QosProfile(), new_guid(), FakeClock()))[1] == 1.0
    timed = QosProfile(deadline_s=0.2)
    assert tick_intervals_s(ReaderMachine("t/a", timed, new_guid(), FakeClock()))[1] == (
        pytest.approx(0.02)
    )
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    got: list[bytes] = []
    reader = Reader(b, "t/quiet", QosProfile(), on_data=lambda payload, _info: got.append(payload))
    writer = Writer(a, "t/quiet", QosProfile(heartbeat_period_s=0.05))
    machine = reader._channel.machine
    ticks: list[float] = []
    tick = machine.tick

    def counting(backlog: int = 0) -> list[Any]:
        ticks.append(time.monotonic())
        return tick(backlog)

    try:
        wait_until(lambda: writer.matched_count == 1, what="match")
        writer.write(b"x")
        wait_until(lambda: got == [b"x"], what="delivery")
        with reader._channel.lock:
            machine.tick = counting  # type: ignore[method-assign]
        time.sleep(1.0)  # deliberately: the wakes of an idle second
        assert len(ticks) <= 3, ticks  # 20 with the 50 ms cap
    finally:
        writer.close()
        reader.close()
        a.close()
        b.close()


def test_a_retuned_deadline_shortens_an_idle_writer_s_sleep() -> None:
    """An idle writer sleeps until its heartbeat (1 s here); a QoS assignment that gives it a
    deadline must make it wake often enough to notice a missed one (a tenth of the deadline)."""
    bus = MemoryBus()
    a = MemoryTransport(bus)
    writer = Writer(a, "t/retuned", QosProfile(heartbeat_period_s=1.0))
    ticks = count_ticks(writer)
    try:
        time.sleep(0.5)  # deliberately: an idle half second
        assert len(ticks) <= 2, ticks
        writer.retune(depth=10, deadline_s=0.2)
        ticks.clear()
        time.sleep(0.5)  # deliberately: wakes every 20 ms now
        assert len(ticks) >= 10, ticks
    finally:
        writer.close()
        a.close()


@pytest.mark.callback_errors_expected
def test_a_batch_s_samples_each_get_their_info_and_one_that_raises_does_not_lose_the_rest() -> None:
    """A batch reaches the reader as one run (``DeliverRun``), delivered sample by sample: each
    with its own seq and stamp, and a callback that raises on one is counted and the run goes
    on."""
    got: list[DataInfo] = []

    def on_data(payload: bytes, info: DataInfo) -> None:
        got.append(info)
        if payload == b"c":  # the middle of the batch's run
            raise RuntimeError("on purpose")

    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, batch_max_delay_s=10.0)
    with _pair("t/run", "t/run", qos, on_data) as (reader, writer):
        stamps = [1_000, 2_000, 3_000, 4_000]
        writer.write(b"a", stamp_ns=stamps[0])  # goes alone (the first after a pause)
        for payload, stamp in zip((b"b", b"c", b"d"), stamps[1:], strict=True):
            writer.write(payload, stamp_ns=stamp)  # these three wait in one batch
        writer.flush()
        wait_until(lambda: len(got) == 4, what="every sample")
        assert [(i.seq, i.stamp_ns, i.writer) for i in got] == [
            (seq, stamp, writer.guid) for seq, stamp in zip(range(1, 5), stamps, strict=True)
        ]
        assert reader.stats().callback_errors == 1


def test_on_data_run_takes_whole_in_order_runs_instead_of_on_data() -> None:
    """A batching writer's runs reach ``on_data_run`` whole, in order, and ``on_data`` never;
    a run whose consumer raises is counted and the next one still arrives."""
    runs: list[tuple[str, list[bytes]]] = []
    singles: list[bytes] = []

    def on_run(key: str, payloads: Sequence[bytes]) -> None:
        runs.append((key, list(payloads)))
        if len(runs) == 1:
            raise RuntimeError("the first run's consumer fails")

    bus = MemoryBus()
    with (
        _nullctx(MemoryTransport(bus)) as a,
        _nullctx(MemoryTransport(bus)) as b,
        Reader(
            b,
            "f/robot/*/sensor/*",
            QOS_RELIABLE_ALL,
            lambda payload, _info: singles.append(payload),
            on_data_run=on_run,
        ) as reader,
        Writer(a, "f/robot/r1/sensor/lidar", QOS_RELIABLE_ALL) as writer,
    ):
        wait_until(lambda: writer.matched_count == 1 and reader.matched_count == 1, what="match")
        wait_until(lambda: writer.wait_for_acknowledgments(0.01), what="sync")
        for i in range(500):
            writer.write(b"%d" % i)
        wait_until(lambda: sum(len(p) for _, p in runs) == 500, what="all samples")
        assert [x for _, payloads in runs for x in payloads] == [b"%d" % i for i in range(500)]
        assert {key for key, _ in runs} == {"f/robot/r1/sensor/lidar"}
        assert len(runs) < 500  # batches arrived as runs, not one sample at a time
        assert singles == []
        assert reader.stats().callback_errors == 1


def test_a_reader_without_a_callback_is_refused() -> None:
    with pytest.raises(ValueError, match="on_data or on_data_run"):
        Reader(MemoryTransport(MemoryBus()), "f/robot/*/sensor/*", QOS_RELIABLE_ALL, None)


def test_a_reader_s_backlog_is_how_long_its_oldest_waiting_sample_waited() -> None:
    """What the CEDDP reports as its ingest backlog (CeddpStats.ingest_backlog_ms): samples
    written while on_data is busy wait in the transport's queue; the next pull measures the
    oldest. The interval's maximum resets when taken; the run's worst stays."""
    slow = SlowFirstDelivery(busy_s=0.3)
    with _pair("t/x", "t/x", QOS_RELIABLE_ALL, slow) as (reader, writer):
        slow.queue_behind(writer.write)
        waited = reader.take_backlog_ms()
        assert 200 <= waited < 5000, waited  # written about 0.3 s before the pull took them
        assert reader.take_backlog_ms() == 0.0  # nothing waited since
        assert reader.worst_backlog_ms == waited


def test_a_callback_that_raises_on_every_sample_is_counted_each_time_and_logged_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A traceback per sample filled 27 MB of log in 30 s and, on a pipe nobody read, blocked
    the channel's thread (issue 17): each failure is counted, the log gets the first traceback
    and then at most a line per 10 s per cause, and the reader goes on acknowledging."""

    def on_data(payload: bytes, info: DataInfo) -> None:
        raise ValueError(f"not a sample I know: {payload!r}")

    qos = QosProfile(history=HistoryPolicy.KEEP_ALL)
    with (
        caplog.at_level(logging.ERROR, logger="arpz.channel"),
        _pair("t/bad", "t/bad", qos, on_data) as (reader, writer),
    ):
        for n in range(500):
            writer.write(b"x%d" % n)
        assert writer.wait_for_acknowledgments(10.0)
        wait_until(lambda: reader.stats().callback_errors == 500, what="500 errors counted")
        records = [r for r in caplog.records if "on_data raised" in r.getMessage()]
        assert 1 <= len(records) <= 2, [r.getMessage() for r in records]
        assert records[0].exc_info is not None and "ValueError" in records[0].getMessage()
        assert all(r.exc_info is None for r in records[1:])  # one traceback


@pytest.mark.callback_errors_expected
def test_a_timer_that_raises_is_counted_and_the_channel_goes_on() -> None:
    """A bug in the machine's timers (issue 17: a KeyError in a reader's tick under overload)
    ended the channel's thread: that reader never acknowledged or delivered again, silently.
    Now it is counted in ``callback_errors``, logged, and the next tick runs as usual."""
    got: list[bytes] = []
    with _pair("t/tick", "t/tick", QOS_RELIABLE_ALL, lambda p, _i: got.append(p)) as (
        reader,
        writer,
    ):
        machine = reader._channel.machine
        tick = machine.tick
        raised: list[int] = []

        def failing_once(backlog: int = 0) -> Any:
            if not raised:
                raised.append(1)
                raise KeyError("on purpose")
            return tick(backlog)

        machine.tick = failing_once  # type: ignore[method-assign]
        reader._channel.wake()
        wait_until(lambda: reader.stats().callback_errors == 1, what="the error counted")
        for i in range(50):
            writer.write(b"%d" % i)
        wait_until(lambda: len(got) == 50, what="samples after the error")
        assert writer.wait_for_acknowledgments(2.0)  # the reader still acknowledges
        assert reader._channel._worker.is_alive()


def test_acknowledged_through_never_waits_for_the_state_lock() -> None:
    """A robot asks once a sample, on its sensing thread; while the channel's worker holds the
    state lock (an ACKNACK being handled) it gets the last figure at once, a lower bound."""
    with _pair("f/robot/*/sensor/*", "f/robot/r1/sensor/imu", QOS_RELIABLE_ALL, _ignore) as (
        _reader,
        writer,
    ):
        for i in range(3):
            writer.write(b"%d" % i)
        wait_until(lambda: writer.acknowledged_through() == 3, what="3 acknowledged")
        with writer._lock:  # held, as the worker holds it while it handles an ACKNACK
            answers: list[tuple[int, float]] = []

            def ask() -> None:
                start = time.monotonic()
                answers.append((writer.acknowledged_through(), time.monotonic() - start))

            asker = threading.Thread(target=ask)
            asker.start()
            asker.join(timeout=2.0)
            assert not asker.is_alive(), "acknowledged_through waited for the state lock"
        assert answers[0][0] == 3 and answers[0][1] < 0.5, answers
        writer.write(b"3")
        wait_until(lambda: writer.acknowledged_through() == 4, what="the 4th acknowledged")


def _ignore(payload: bytes, info: DataInfo) -> None:
    del payload, info


class _PutThreads(MemoryTransport):
    """Notes the thread of every put (a reader puts only control traffic: ACKNACKs, NACKs)."""

    def __init__(self, bus: MemoryBus) -> None:
        super().__init__(bus)
        self.put_threads: list[str] = []

    def put(
        self, key: str, payload: bytes, *, attachment: bytes | None = None, bulk: bool = False
    ) -> None:
        self.put_threads.append(threading.current_thread().name)
        super().put(key, payload, attachment=attachment)


def test_a_delivery_pass_leaves_its_acknacks_to_the_control_thread() -> None:
    """A put gives the GIL up, and the delivery thread would wait to take it back with the pass's
    samples held (the CEDDP's sensor path, issue 17): its ACKNACKs go out on the control thread.
    Heartbeats ride on the data here, as a fleet's robots send them, so the delivery thread is
    the one that decides to acknowledge."""
    bus = MemoryBus()
    reader_side = _PutThreads(bus)
    got: list[int] = []
    qos = msgspec.structs.replace(QOS_RELIABLE_ALL, piggyback_heartbeats=True)
    with (
        Reader(reader_side, "f/robot/*/sensor/*", qos, lambda p, i: got.append(i.seq)) as reader,
        Writer(MemoryTransport(bus), "f/robot/r1/sensor/imu", qos) as writer,
    ):
        wait_until(lambda: writer.matched_count == 1 and reader.matched_count == 1, what="match")
        for i in range(50):
            writer.write(b"%d" % i)
        assert writer.wait_for_acknowledgments(5.0)
        wait_until(lambda: len(got) == 50, what="50 delivered")
    threads = set(reader_side.put_threads)
    assert threads, "the reader sent no ACKNACK"
    assert "arpz-reader-f/robot/*/sensor/*" not in threads, threads
    assert threads == {"arpz-reader-f/robot/*/sensor/*/control"}, threads
