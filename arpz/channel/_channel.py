"""Runs one pure machine over a ``Transport``: subscriptions, tokens, worker threads, timers.

Zenoh callbacks only enqueue (zenoh-python's advice: never block or call Zenoh from its threads);
the worker thread runs the machine, publishes what it asks, and calls the event callbacks. The
queue is bounded and every item it refuses is counted: a reliable reader gets a refused sample
again by NACK, a best-effort one reports it lost through the seq gap.

A reader's data takes a shorter path: a delivery thread blocks in a Zenoh FIFO (no Python
callback on Zenoh's thread, no GIL handoff between two Python threads per sample: with the
callback-and-queue hop the 1 kHz round trip was 1.36-1.38x raw Zenoh's, without it about 1.2x,
benchmarks/RESULTS.md), runs the machine and calls ``on_data``. Samples the worker delivers
(recovered by NACK, released by a timeout) take turns with it (``_Turns``): ``on_data`` is never
called twice at once, and always in the order the machine decided.
"""

from __future__ import annotations

import logging
import math
import queue
import sys
import threading
import time
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any, Self, TypeVar

import msgspec

from arpz.core.protocol.actions import Action, Deliver, DeliverRun, Notify, Send, TokenChange
from arpz.core.protocol.events import DataInfo
from arpz.core.protocol.reader_machine import ReaderMachine
from arpz.core.protocol.timers import BacklogMeter, SojournMeter, WaitMeter
from arpz.core.protocol.writer_machine import QUIET_HEARTBEAT_S, WriterMachine
from arpz.core.throttled_log import ThrottledLog
from arpz.core.transport import Handle, PullSubscriber, Transport, TransportError

log = logging.getLogger("arpz.channel")

#: items waiting for the worker; beyond this the transport thread drops and counts
MAX_QUEUE = 200_000
_BATCH = 512
_STOP = object()
#: what an inline reader performs on the transport's thread, and a reader's delivery thread on
#: its own (the rest goes to the worker)
_DELIVERIES = (Deliver, DeliverRun)
#: a reader's data waiting in its Zenoh FIFO; beyond this Zenoh stops reading the link
#: (backpressure to the writers, nothing dropped)
PULL_CAPACITY = 20_000


class _Turns:
    """Runs passes one at a time in the order their tickets were taken. A ticket is taken with
    the machine's lock held, so turns follow the machine's decisions; a turn is waited for and run
    without it, so ``on_data`` may call ``stats()``. A stuck ``on_data`` holds every later turn
    back: the channel stops acknowledging, as one thread would, and KEEP_ALL writers block."""

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._next = 0
        self._serving = 0
        self._waiting = 0

    def take(self) -> int:
        """Call with the machine's lock held; every ticket taken must be run."""
        ticket = self._next
        self._next += 1
        return ticket

    def run(
        self, ticket: int, perform: Callable[[list[Action]], None], actions: list[Action]
    ) -> None:
        cond = self._cond
        # Read without the lock: once ``_serving`` equals this ticket, only this thread moves it
        # on, so an equal read is final; an unequal one is checked again under the lock.
        if self._serving != ticket:
            with cond:
                self._waiting += 1
                while self._serving != ticket:
                    cond.wait()
                self._waiting -= 1
        try:
            perform(actions)
        finally:
            with cond:
                self._serving += 1
                if self._waiting:
                    cond.notify_all()


_TOKEN = object()
_POST = object()
#: the longest a worker sleeps with nothing to do (a writer's next heartbeat comes sooner): a
#: quiet writer's timer horizon, so that neither wakes the worker the other does not
MAX_IDLE_S = QUIET_HEARTBEAT_S


def _heartbeat_at(writer: WriterMachine) -> float:
    """When (``time.monotonic``) the writer's heartbeat timer fires; its clock may be another.

    Its clock is read first and ``time.monotonic`` after it, so that with the same clock the
    answer is never before the heartbeat is due. Reading "now" first, before the tick that
    set the timer, woke the worker as early as the tick and its lock had taken (on a loaded
    CI host, long enough for a quiet writer to wake twice, 0.2 ms apart)."""
    remaining = writer.next_heartbeat_s - writer.clock.monotonic_s()
    return time.monotonic() + max(0.0, remaining)


def tick_intervals_s(machine: WriterMachine | ReaderMachine) -> tuple[float, float]:
    """(fine, idle) timer periods. The fine one serves pending NACKs and give-ups; when nothing
    is pending the worker sleeps for the idle one, so an idle channel does not wake 500 times a
    second and take the GIL from the threads that carry data."""
    qos = machine.qos
    if isinstance(machine, WriterMachine):
        # a writer sends no NACKs (their delay is the reader's): its fine timer repeats SYNC,
        # every nack_period_s. A streaming writer ticks at it; at the reader's nack_delay_s
        # each of a publisher's 18 bulk writers (20 ms batches) woke every 2 ms
        # (benchmarks/ceddp_ingest.py, issue 17).
        fine = min(0.05, max(0.001, qos.nack_period_s))
        # Idle, it wakes for its heartbeat (``_run`` aims at the machine's next one) and for
        # its offered deadline, liveliness lease and lifespan; not every 50 ms besides: a CEDDP
        # keeps a Hello writer per robot, 25 of them woke 500 times a second (issue 17).
        periods = [MAX_IDLE_S]
        lasting: tuple[float, ...] = (qos.deadline_s, qos.lease_duration_s, qos.lifespan_s)
    else:
        fine = min(0.05, max(0.001, min(qos.nack_delay_s or qos.nack_period_s, qos.nack_period_s)))
        # Idle, nothing is pending (``ReaderMachine.busy`` is false, and whichever thread runs
        # the machine wakes the worker the moment it is not): only the requested deadline and
        # lease need polling. A robot keeps four readers; each woke 20 times a second.
        periods = [MAX_IDLE_S]
        lasting = (qos.deadline_s, qos.lease_duration_s)
    periods += [value / 10 for value in lasting if value > 0]
    if qos.batching:  # an open batch must go out within about its delay
        fine = min(fine, qos.batch_max_delay_s)
    return fine, max(fine, min(periods))


class Channel:
    def __init__(
        self,
        transport: Transport,
        machine: WriterMachine | ReaderMachine,
        events: object,
        on_data: Callable[[bytes, DataInfo], None] | None,
        name: str,
        *,
        inline: bool = False,
        before_tick: Callable[[], None] | None = None,
        on_data_run: Callable[[str, Sequence[bytes]], None] | None = None,
        bulk: bool = False,
    ) -> None:
        self.transport = transport
        #: what this end sends yields to the session's other traffic (``Transport.publisher``)
        self.bulk = bulk
        self.inline = inline
        #: runs on the worker with the lock held before each ``machine.tick`` (the writer sends
        #: a due batch there, so that it goes out in order with the writes)
        self.before_tick = before_tick
        #: when the worker will next tick (monotonic s), set with the lock held: a writer that
        #: opens a batch wakes the worker only if that is too late for the batch's delay
        self.next_tick_s = 0.0
        #: tick at the worker's next pass (set with the lock held): a retune, or a NACK that
        #: waited for the FIFO to drain and is due now
        self._tick_now = False
        self.machine = machine
        self.events = events
        self.on_data = on_data
        #: when set, takes every delivery instead of ``on_data``: a whole in-order run at once
        self.on_data_run = on_data_run
        #: guards the machine; ``cond`` (on the same lock) wakes a KEEP_ALL write waiting for room
        self.mutex = threading.Lock()
        self.lock = threading.Condition(self.mutex)
        self.queue_dropped = 0
        self.callback_errors = 0
        self.name = name
        #: one traceback per cause, then a line per 10 s with the count (see ``_count_error``)
        self._error_log = ThrottledLog(log)
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._handles: list[Handle] = []
        self._tokens: dict[str, Handle] = {}
        self._fine_s, self._idle_s = tick_intervals_s(machine)
        self._closed = False
        #: set by close() before it undeclares: the delivery thread's recv failing is then the end
        self._closing = False
        #: a reader that is not inline pulls its data on a delivery thread of its own
        self._pulls = isinstance(machine, ReaderMachine) and not inline
        self._pull: PullSubscriber | None = None
        self._pull_handler: Callable[[str, bytes, bytes | None], list[Action]] | None = None
        self._turns = _Turns()
        #: the delivery thread left samples in its FIFO at its last pass (lock held)
        self._pull_backlog = False
        #: how long the delivery thread waited for data (blocked in ``recv``): the rest of its
        #: wall time it was working, or waiting for the CPU or the GIL (a server's load)
        self.delivery_wait = WaitMeter()
        #: how long the oldest message of each pull had waited in the transport's queue (the
        #: reader's backlog in time; arpz.core.transport.PullSubscriber.waited_ns)
        self.delivery_backlog = BacklogMeter()
        #: how long each delivered sample had been in this process when its pass ended (an
        #: upper bound: the pass's oldest sample's figure; arpz.core.protocol.timers.SojournMeter)
        self.delivery_sojourn = SojournMeter()
        self._delivery: threading.Thread | None = None
        if self._pulls:
            self._delivery = threading.Thread(target=self._run_delivery, name=name, daemon=True)
            name = f"{name}/control"
        self._worker = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self, token_key: str | None = None) -> None:
        """Subscribe, then declare ``token_key`` (peers may answer at once), then start the
        worker (whose first heartbeat must not precede the token that makes it known)."""
        try:
            for expr, handler_name in self.machine.subscriptions():
                handler = getattr(self.machine, handler_name)
                if self._pulls and handler_name == "on_data":
                    self._pull = self.transport.subscribe_pull(expr, PULL_CAPACITY)
                    self._pull_handler = handler
                    continue
                self._handles.append(self.transport.subscribe(expr, self._enqueuer(handler)))
            self._handles.append(
                self.transport.watch_liveliness(self.machine.watch_expr(), self._on_token)
            )
            if token_key is not None:
                self._tokens[token_key] = self.transport.declare_token(token_key)
        except Exception:
            self._undeclare()
            if self._pull is not None:
                self._pull.undeclare()
            for token in self._tokens.values():
                token.undeclare()
            raise
        self._worker.start()
        if self._delivery is not None:
            self._delivery.start()

    def _enqueuer(
        self, handler: Callable[[str, bytes, bytes | None], list[Action]]
    ) -> Callable[[str, bytes, bytes | None], None]:
        q = self._queue
        if self.inline:

            def run_inline(key: str, payload: bytes, attachment: bytes | None) -> None:
                try:
                    with self.lock:
                        actions = handler(key, payload, attachment)
                        wake = self._worker_needed()
                except Exception:
                    self._count_error("reliable channel: unexpected error")
                    return
                if wake:
                    self.wake()
                # deliveries here; ACKNACKs, NACKs, events and tokens on the worker
                self._perform_here(actions)

            return run_inline

        def enqueue(key: str, payload: bytes, attachment: bytes | None) -> None:
            if q.qsize() >= MAX_QUEUE:
                self.queue_dropped += 1
                return
            q.put((handler, key, payload, attachment))

        return enqueue

    def _perform_here(self, actions: list[Action]) -> None:
        """Deliver on this thread; post the rest (ACKNACKs, NACKs, events) to the worker.

        Why the ACKNACKs leave this thread: a put gives up the GIL, and taking it back waits
        for whichever thread took it meanwhile, up to the interpreter's switch interval (5 ms)
        and more on a loaded host. A CEDDP's sensor reader acknowledges hundreds of writers a
        second, so its delivery passes queued several times each behind the GIL: with the
        puts moved to the worker, "time in the CEDDP" at 50 robots fell from 48-57 to 11-13
        ms at p99 with the host in a slow window (``python benchmarks/fleet_ab.py``, three
        rounds, issue 17; in a fast one within the noise). An ACKNACK leaves a little later;
        what it acknowledges is unchanged."""
        deliveries = [a for a in actions if type(a) in _DELIVERIES]
        if deliveries:
            self.perform(deliveries)
        if len(deliveries) < len(actions):
            self.post([a for a in actions if type(a) not in _DELIVERIES])

    def _worker_needed(self) -> bool:
        """Lock held, after the machine ran on another thread than the worker: the machine now
        needs the fine timer (a gap to NACK within nack_delay_s) but the worker sleeps longer."""
        return self.next_tick_s > time.monotonic() + self._fine_s and self.machine.busy()

    def _run_delivery(self) -> None:
        """The reader's delivery thread: pull data from the FIFO in batches, run the machine on
        them under one lock acquisition, then deliver in turn."""
        pull, handler = self._pull, self._pull_handler
        assert pull is not None and handler is not None
        recv, try_recv, waited_ns = pull.recv, pull.try_recv, pull.waited_ns
        wait, backlog, sojourn = self.delivery_wait, self.delivery_backlog, self.delivery_sojourn
        since = time.perf_counter_ns
        reader = self.machine if isinstance(self.machine, ReaderMachine) else None
        clock = self.machine.clock.monotonic_s
        while True:
            try:
                first = try_recv()
                if first is None:
                    # the FIFO is empty: a heartbeat seen while we wait has no data behind it
                    if reader is not None and reader.drain_waited:
                        with self.lock:
                            wake = reader.drained(math.inf)
                            if wake:  # the NACK that waited is due now, not a fine tick later
                                self._tick_now = True
                        if wake:
                            self.wake()
                    elif reader is not None:
                        reader.drained_s = math.inf
                    wait.start()
                    first = recv()
                    wait.stop()
                    if reader is not None:  # more may be queued behind it
                        reader.drained_s = clock()
                    waited = waited_ns()
                else:  # it queued while we worked: how long is our backlog, in time
                    waited = waited_ns()
                    backlog.observe(waited)
                taken_at = since()
                items = [first]
            except TransportError:  # undeclared by close() and drained, or the session went away
                wait.stop()
                if self._closing:
                    log.debug("reliable channel: delivery thread stops", exc_info=True)
                else:  # nothing more is delivered: say so loudly (the transport closed first?)
                    self.callback_errors += 1
                    log.error(
                        "reliable channel %s: data receive failed, delivery stopped",
                        self._delivery.name if self._delivery else "?",
                        exc_info=True,
                    )
                return
            empty_at: float | None = None
            while len(items) < _BATCH:
                before = clock()
                try:
                    item = try_recv()
                except TransportError:  # closed meanwhile: handle what came, recv says the rest
                    break
                if item is None:
                    empty_at = before
                    break
                items.append(item)
            out: list[Action] = []
            with self.lock:
                if reader is not None:
                    # a full pull leaves more queued: a NACK now would ask for some of it
                    reader.queued = len(items) >= _BATCH
                    # more than one message waited for us: we are behind (ReaderMachine)
                    reader.fifo_behind = len(items) > 1
                for item in items:
                    try:
                        out.extend(handler(item[0], item[1], item[2]))
                    except Exception:
                        self._count_error("reliable channel delivery: unexpected error")
                self._pull_backlog = len(items) >= _BATCH
                drained = reader is not None and empty_at is not None and reader.drained(empty_at)
                if drained:  # a NACK that waited for the drain is due now, not a fine tick later
                    self._tick_now = True
                ticket = self._ticket(out)
                wake = drained or self._worker_needed()
            if wake:
                self.wake()
            if ticket is not None:
                self._turns.run(ticket, self._perform_here, out)
            elif out:
                self._perform_here(out)
            # the pass's oldest sample: its wait before the pull, and the pass since
            sojourn.observe(None if waited is None else waited + since() - taken_at, len(items))

    def _ticket(self, actions: list[Action]) -> int | None:
        """Lock held: a turn for a pass that delivers (a reader with a delivery thread only)."""
        if self._pulls and any(type(a) in _DELIVERIES for a in actions):
            return self._turns.take()
        return None

    def _on_token(self, key: str, alive: bool) -> None:
        self._queue.put((_TOKEN, key, alive, None))

    def retimed(self) -> None:
        """The machine's QoS changed (a retune, the lock held): its timer periods follow, and
        the worker ticks now rather than at the end of a sleep timed by the old QoS."""
        self._fine_s, self._idle_s = tick_intervals_s(self.machine)
        self._tick_now = True
        self.wake()

    def wake(self) -> None:
        """Make the worker look at the machine now (it may have become busy)."""
        self._queue.put((_POST, [], None, None))

    def post(self, actions: Sequence[Action]) -> None:
        """Run actions on the worker thread (event callbacks never run on the caller's thread)."""
        if actions:
            self._queue.put((_POST, list(actions), None, None))

    def _run(self) -> None:
        q = self._queue
        next_tick = 0.0
        writer = self.machine if isinstance(self.machine, WriterMachine) else None
        while True:
            try:
                batch = [q.get(timeout=max(0.0, next_tick - time.monotonic()))]
            except queue.Empty:
                batch = []
            # Drain what is already queued and run it under one lock acquisition: at high rates
            # this is what keeps the worker ahead of the transport thread.
            while batch and len(batch) < _BATCH:
                try:
                    batch.append(q.get_nowait())
                except queue.Empty:
                    break
            stop = any(item is _STOP for item in batch)
            if batch:
                todo: list[Action] = []
                with self.lock:
                    for item in batch:
                        head: Any = item if item is _STOP else item[0]
                        if head is _STOP:
                            continue
                        if head is _POST or head is _TOKEN:
                            todo.extend(self._dispatch(item))
                            continue
                        try:  # the hot path: a sample or a control message for the machine
                            todo.extend(head(item[1], item[2], item[3]))
                        except Exception:
                            self._count_error("reliable channel worker: unexpected error")
                    if writer is not None:
                        self.lock.notify_all()  # a KEEP_ALL write may be waiting for room
                        next_tick = min(next_tick, _heartbeat_at(writer))
                    if self.machine.busy():
                        next_tick = min(next_tick, time.monotonic() + self._fine_s)
                    if self._tick_now:
                        self._tick_now, next_tick = False, 0.0
                    self.next_tick_s = next_tick
                    ticket = self._ticket(todo)
                self._perform_in_turn(ticket, todo)
            if stop:
                return
            now = time.monotonic()
            if now >= next_tick:
                with self.lock:
                    if self.before_tick is not None:
                        self._call(self.before_tick)
                    # samples still in the delivery thread's FIFO may be the missing ones
                    backlog = q.qsize() + (_BATCH if self._pull_backlog else 0)
                    try:
                        actions = self.machine.tick(backlog)
                    except Exception:  # a bug must not end the worker: counted, logged
                        self._count_error("reliable channel timer: unexpected error")
                        actions = []
                    next_tick = now + (self._fine_s if self.machine.busy() else self._idle_s)
                    if writer is not None:
                        next_tick = min(next_tick, _heartbeat_at(writer))
                    self.next_tick_s = next_tick
                    ticket = self._ticket(actions)
                self._perform_in_turn(ticket, actions)

    def _perform_in_turn(self, ticket: int | None, actions: list[Action]) -> None:
        if ticket is None:
            self.perform(actions)
        else:
            self._turns.run(ticket, self.perform, actions)

    def _dispatch(self, item: tuple[Any, Any, Any, Any]) -> list[Action]:
        """Run one queued item through the machine (the lock is held); never raises."""
        head, a, b, c = item
        try:
            if head is _POST:
                result: list[Action] = a
                return result
            if head is _TOKEN:
                if isinstance(self.machine, WriterMachine):
                    return self.machine.on_reader_token(a, b)
                return self.machine.on_writer_token(a, b)
            result = head(a, b, c)
            return result
        except Exception:  # a bug must not kill the worker and silently stop the channel
            self._count_error("reliable channel worker: unexpected error")
            return []

    def perform(self, actions: list[Action]) -> None:
        on_data, on_run = self.on_data, self.on_data_run
        for action in actions:
            kind = type(action)
            if on_run is not None and (kind is DeliverRun or kind is Deliver):
                self._deliver_whole(on_run, action)  # type: ignore[arg-type]
            elif kind is DeliverRun:
                if on_data is not None:
                    self._deliver_run(on_data, action)  # type: ignore[arg-type]
            elif kind is Deliver:
                if on_data is not None:
                    try:
                        on_data(action.payload, action.info)  # type: ignore[union-attr]
                    except Exception:
                        self._on_data_raised()
            elif kind is Send:
                try:
                    if self.bulk:
                        self.transport.put(
                            action.key,  # type: ignore[union-attr]
                            action.payload,  # type: ignore[union-attr]
                            attachment=action.attachment,  # type: ignore[union-attr]
                            bulk=True,
                        )
                    else:
                        self.transport.put(action.key, action.payload, attachment=action.attachment)  # type: ignore[union-attr]
                except TransportError as exc:  # a closed session during shutdown
                    log.debug("put on %s failed: %s", action.key, exc)  # type: ignore[union-attr]
            elif kind is Notify:
                self._call(getattr(self.events, action.event, None), action.status)  # type: ignore[union-attr]
            elif kind is TokenChange:
                self._token(action)  # type: ignore[arg-type]

    def _deliver_run(self, on_data: Callable[[bytes, DataInfo], None], run: DeliverRun) -> None:
        """Each sample of the run to ``on_data``, with its own ``DataInfo``. A loop here rather
        than over ``DeliverRun.samples()``, whose generator took 1.3-1.4x as long at one sample
        a message (what robots at 100 Hz send: about 0.3 us of the CEDDP's 20 a message) and
        about 2x a sample in a batch (``python benchmarks/investigations/delivery_cost.py``; issue
        17)."""
        key, writer, retransmitted, seq = run.key, run.writer, run.retransmitted, run.first
        for stamp, payload in zip(run.stamps, run.payloads, strict=True):
            try:
                on_data(payload, DataInfo(key, writer, seq, stamp, retransmitted))
            except Exception:
                self._on_data_raised()
            seq += 1

    def _deliver_whole(
        self, on_run: Callable[[str, Sequence[bytes]], None], action: DeliverRun | Deliver
    ) -> None:
        if isinstance(action, DeliverRun):
            self._call(on_run, action.key, action.payloads)
        else:
            self._call(on_run, action.info.key, (action.payload,))

    def _on_data_raised(self) -> None:
        self._count_error("on_data raised; the channel goes on")

    def _count_error(self, message: str) -> None:
        """Count the exception being handled in ``callback_errors`` and log it, throttled per
        message and exception type: its first traceback, then at most a line per 10 s with how
        many came meanwhile. A callback that raised on every sample logged a traceback each (27
        MB in 30 s of one robot's sensor stream); with stderr on a pipe nobody read, the
        channel's thread then blocked writing the log and the reader stopped acknowledging."""
        self.callback_errors += 1
        exc = sys.exc_info()[1]
        kind = type(exc).__name__
        self._error_log.exception(
            f"{message} {kind}", "%s: %s (%s: %s)", self.name, message, kind, exc
        )

    def _call(self, callback: Callable[..., None] | None, *args: object) -> None:
        if callback is None:
            return
        try:
            callback(*args)
        except Exception:
            self._count_error("user callback raised; the channel goes on")

    def _token(self, change: TokenChange) -> None:
        if change.declare and change.key not in self._tokens and not self._closed:
            self._tokens[change.key] = self.transport.declare_token(change.key)
        elif not change.declare and change.key in self._tokens:
            self._tokens.pop(change.key).undeclare()

    def _undeclare(self) -> None:
        handles, self._handles = self._handles, []
        for handle in reversed(handles):
            handle.undeclare()

    def close(self) -> None:
        """Undeclare subscriptions first (no new callbacks), then stop the worker, then tokens."""
        if self._closed:
            return
        self._undeclare()
        self._queue.put(_STOP)
        here = threading.current_thread()
        if self._worker.is_alive() and here is not self._worker:
            self._worker.join(timeout=5.0)
        if self._pull is not None:
            self._closing = True
            self._pull.undeclare()  # the delivery thread's recv raises once the FIFO is drained
            delivery = self._delivery
            if delivery is not None and delivery.is_alive() and here is not delivery:
                delivery.join(timeout=5.0)
        self._closed = True
        tokens, self._tokens = self._tokens, {}
        for handle in tokens.values():
            handle.undeclare()


S = TypeVar("S", bound=msgspec.Struct)


class Endpoint:
    """What Writer and Reader share: a channel, counted stats, idempotent close, ``with``."""

    _channel: Channel
    _closed: bool = False

    def _with_counters(self, stats: S) -> S:
        return msgspec.structs.replace(
            stats,
            queue_dropped=self._channel.queue_dropped,
            callback_errors=self._channel.callback_errors,
        )

    def _on_close(self) -> None:
        """Undeclare what the subclass declared beside the channel."""

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._channel.close()
        self._on_close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
