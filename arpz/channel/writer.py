"""``Writer``: the publishing end of a reliable channel over any ``Transport``."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TypeVar

import msgspec

from arpz.channel._channel import Channel, Endpoint
from arpz.core.link_sizes import writer_fragment_bytes
from arpz.core.protocol._common import new_guid
from arpz.core.protocol.events import WriterEventCallbacks
from arpz.core.protocol.qos import QosProfile
from arpz.core.protocol.timers import Clock, SystemClock
from arpz.core.protocol.writer_machine import HistoryFullError, WriterMachine, WriterStats
from arpz.core.transport import HoldingPublisher, Transport

_W = TypeVar("_W")


class Writer(Endpoint):
    """Publishes opaque payloads on ``key`` with the QoS of ``qos``.

    The payload goes unchanged on ``key`` and the DATA header in the Zenoh attachment, so a plain
    Zenoh subscriber still decodes the samples; control traffic stays on keys below ``key``.

    ``block``: Zenoh congestion control of the data. True (BLOCK) gives backpressure: ``write``
    waits while Zenoh's queue towards the router is full, which suits bulk transfer. False (DROP)
    keeps ``write`` from ever waiting on Zenoh (RTPS semantics: KEEP_LAST never blocks, KEEP_ALL
    only on its own full history): a sample Zenoh drops is recovered by NACK like one the link
    lost, or reported lost. Robots use False, so a stalled server never stalls their sensing
    (Zenoh blocks a BLOCK put up to 5 s and then closes the link).

    ``bulk``: this writer's messages and resends yield to the session's other traffic on a busy
    link (``Transport.publisher``): a camera's frames, so that a link the frames saturate
    still carries the robot's small sensors, reports and clock exchanges (issue 39).

    ``express``: every sample leaves at once as its own message, batched neither by Zenoh nor by
    arpz (``batch_max_samples`` is taken as 1): the choice for latency. Adaptive write batching
    only batches samples written less than ``batch_max_delay_s`` apart, but at 1 kHz a scheduling
    hiccup does that often enough to add its delay to the p99 round trip.

    ``fragment_bytes``: a sample longer than this is sent as fragments of this size, each its
    own Zenoh message (DATA_FRAG), reassembled by the readers; only the fragments a reader
    misses are resent, and the sample is still one seq, delivered whole or counted lost once.
    None: the transport's ``fragment_bytes`` if it has one (its link's:
    ``arpz.core.link_sizes.link_sizes``), else one UDP datagram's worth, safe on every link; on a
    datagram link it is cut down so that a fragment resent on this writer's key still fits one
    datagram (``arpz.core.link_sizes.writer_fragment_bytes``).
    """

    def __init__(
        self,
        transport: Transport,
        key: str,
        qos: QosProfile,
        *,
        events: WriterEventCallbacks | None = None,
        express: bool = False,
        block: bool = True,
        clock: Clock | None = None,
        fragment_bytes: int | None = None,
        bulk: bool = False,
    ) -> None:
        if express and qos.batching:
            qos = msgspec.structs.replace(qos, batch_max_samples=1)
        self.key = key
        if fragment_bytes is None:
            link: int | None = getattr(transport, "fragment_bytes", None)
            fragment_bytes = writer_fragment_bytes(key, link)
        #: a sample longer than this is sent as fragments
        self.fragment_bytes = fragment_bytes
        self._machine = WriterMachine(
            key, qos, new_guid(), clock or SystemClock(), fragment_bytes=fragment_bytes
        )
        self.guid = self._machine.hex
        self._channel = Channel(
            transport,
            self._machine,
            events or WriterEventCallbacks(),
            None,
            f"arpz-writer-{key}",
            before_tick=self._send_due_batch if qos.batching else None,
            bulk=bulk,
        )
        self._publisher = transport.publisher(key, express=express, block=block, bulk=bulk)
        self._lock = self._channel.lock
        self._mutex = self._channel.mutex
        self._acquire, self._release = self._mutex.acquire, self._mutex.release
        #: with ``note_audience`` set, whether the last ``write`` had a reader matched or away
        #: (taken under the lock that orders the write, so a match that begins or resumes at
        #: that moment is on one side of it: the downlink's count of commands written to no one)
        self.note_audience = False
        self.last_write_had_audience = True
        #: ``acknowledged_through``'s last figure
        self._acked_through = 0
        self._acked_epoch = -1  # the machine's ack_epoch when _acked_through was taken
        #: held from taking a message under the state lock until its put returns: the order
        #: of puts is the order of seqs (lock order: state lock, then this one, never reversed)
        self._send_lock = threading.Lock()
        self._machine_write = self._machine.write
        self._put = self._publisher.put
        #: a bundling publisher (arpz.channel.bundling) holds a message until the tick ends: the
        #: machine's heartbeats stop short of it until ``_on_released``, and what this thread
        #: holds is sent before a KEEP_ALL write waits for acknowledgements of it
        publisher = self._publisher
        self._holding: HoldingPublisher | None = (
            publisher if isinstance(publisher, HoldingPublisher) else None
        )
        if self._holding is not None:
            self._holding.on_released = self._on_released
        try:
            self._channel.start(self._machine.token_key)
        except Exception:
            self._publisher.undeclare()
            raise

    def write(self, payload: bytes, *, stamp_ns: int | None = None) -> int:
        """Publish one sample and return its seq (1, 2, ...).

        KEEP_ALL: blocks while the history is full of unacknowledged samples, up to
        ``max_blocking_time_s``, then raises ``HistoryFullError`` (nothing is dropped silently).
        ``stamp_ns`` is the source time (wall clock, ns): lifespan is measured from it.
        """
        if self._closed:
            raise RuntimeError(f"write on closed writer {self.key}")
        if len(payload) > self.fragment_bytes:
            return self._write_large(payload, stamp_ns)
        # bound acquire/release rather than ``with``: fewer lookups on the hottest path
        self._acquire()
        try:
            machine, holding = self._machine, self._holding
            if self.note_audience:  # under the lock that orders the write: no race with a match
                self.last_write_had_audience = machine.has_audience
            # the first seq not yet put: what ``ready`` starts with, if the publisher holds it
            unsent = machine.last_seq - len(machine.batch) + 1 if holding is not None else 0
            try:
                seq, ready, actions = self._machine_write(payload, stamp_ns)
            except HistoryFullError:
                self._send_due_batch(force=True)  # readers cannot acknowledge what is unsent
                if holding is not None:
                    holding.release_held()
                seq, ready, actions = self._wait_for_room(
                    lambda: self._machine_write(payload, stamp_ns)
                )
            if len(self._machine.batch) == 1 and self._channel.next_tick_s > (
                self._machine.batch_due_s
            ):
                self._channel.wake()  # a batch opened: the worker sends it if it is not filled
            if ready is not None:
                if (
                    holding is not None
                    and not machine.held_from
                    and holding.will_hold(ready[0], ready[1])
                ):
                    # every seq after the last one put is in ``ready`` or in the open batch,
                    # which follows it: heartbeats stop short of ``ready``'s first
                    machine.held_from = unsent
                # taken before the state lock is released, so messages leave in seq order
                self._send_lock.acquire()
        finally:
            self._release()
        if ready is not None:
            # The put runs outside the state lock: it releases the GIL, and a worker that then
            # blocked on the state lock cost both threads a futex round trip and a GIL handoff
            # for every message (measured: 10-15 % of throughput at 1 KiB).
            try:
                self._put(ready[0], attachment=ready[1])
            finally:
                self._send_lock.release()
        if actions:
            self._channel.post(actions)
        return seq

    def _write_large(self, payload: bytes, stamp_ns: int | None) -> int:
        """``write`` of a sample longer than ``fragment_bytes``: its fragments are put one by
        one, in order, after the open batch; heartbeats announce the sample only once all of
        them are out (``WriterMachine.fragmenting``), so no reader asks for one on its way."""
        machine, holding = self._machine, self._holding
        self._acquire()
        try:
            if self.note_audience:
                self.last_write_had_audience = machine.has_audience
            try:
                seq, messages, actions = machine.write_large(payload, stamp_ns)
            except HistoryFullError:
                self._send_due_batch(force=True)
                if holding is not None:
                    holding.release_held()
                seq, messages, actions = self._wait_for_room(
                    lambda: machine.write_large(payload, stamp_ns)
                )
            machine.fragmenting = seq
            self._send_lock.acquire()
        finally:
            self._release()
        try:
            if holding is not None:  # what the tick holds (older seqs) leaves first
                holding.release_held()
            for data, attachment in messages:
                self._put(data, attachment=attachment)
            if holding is not None:  # and the fragments leave now, not at the tick's end
                holding.release_held()
        finally:
            machine.fragmenting = 0  # a plain store, read by the worker's heartbeat
            self._send_lock.release()
        if actions:
            self._channel.post(actions)
        return seq

    def _on_released(self) -> None:
        """The bundle holding this writer's messages left (or was refused: the samples are in
        the history, and the next heartbeat lets the reader NACK them). Called by the thread
        that set ``held_from`` (the tick's), possibly with the state lock held (a KEEP_ALL
        write sending its open bundle before it waits), so a plain store, not under the lock:
        the worker reading it sees either value, and either is safe."""
        self._machine.held_from = 0

    def _send_due_batch(self, force: bool = False) -> None:
        """Publish the open batch if it is due (or ``force``); call with the lock held."""
        ready = self._machine.flush_batch(force)
        if ready is not None:
            with self._send_lock:
                self._put(ready[0], attachment=ready[1])

    def flush(self) -> None:
        """Publish the open batch now (batching only; otherwise every write is already out)."""
        with self._mutex:
            self._send_due_batch(force=True)

    def _wait_for_room(self, write: Callable[[], _W]) -> _W:
        """KEEP_ALL is full: wait (the lock is held and released by ``wait``) for ACKNACKs."""
        give_up = time.monotonic() + self.qos.max_blocking_time_s
        while True:
            now = time.monotonic()
            if now >= give_up:
                return write()  # raises HistoryFullError again
            self._lock.wait(give_up - now)
            try:
                return write()
            except HistoryFullError:
                continue

    def assert_unchanged(self) -> None:
        """Call when a reading equal to the last one sent is held back (the local cache): the
        topic is proven alive and current to every reader without resending the value."""
        with self._lock:
            actions = self._machine.assert_unchanged()
        self._channel.post(actions)

    @property
    def qos(self) -> QosProfile:
        """The QoS in force: the machine's, which ``retune`` changes (the one place it lives)."""
        return self._machine.qos

    def retune(
        self, *, depth: int, deadline_s: float, heartbeat_period_s: float | None = None
    ) -> None:
        """Change the KEEP_LAST depth, the offered deadline and (unless None) the heartbeat
        period in place (a QoS assignment)."""
        with self._lock:
            actions = self._machine.retune(
                depth=depth, deadline_s=deadline_s, heartbeat_period_s=heartbeat_period_s
            )
            self._channel.retimed()  # a new heartbeat or deadline: the worker's sleep follows
        self._channel.post(actions)

    def assert_liveliness(self) -> None:
        """MANUAL_BY_TOPIC: prove the writer alive without writing."""
        with self._lock:
            actions = self._machine.assert_liveliness()
        self._channel.post(actions)

    def wait_for_acknowledgments(self, timeout_s: float) -> bool:
        """True once every matched reliable reader acknowledged everything written."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            self._send_due_batch(force=True)
            while not self._machine.all_acknowledged():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._lock.wait(min(remaining, 0.05))
        return True

    def acknowledged_through(self) -> int:
        """The highest seq every matched reliable reader acknowledged (with all before it), or
        a lower one: while the channel's worker holds the state lock (an ACKNACK being
        handled), the figure of the last call, which this never waits for. A robot asks once a
        sample, on its sensing thread; in a 50-robot fleet worker, waiting for the lock took
        about a tenth of that thread's time (py-spy, issue 17), and taking it a tenth of the
        thread's time with the GIL (py-spy --gil, stop 39), for a figure that changes with an
        ACKNACK, about once a second: the last figure stands, without the lock, while the
        machine's ``ack_epoch`` does. A lower figure is the conservative one: the robot's
        ``since_ns`` then reaches back further."""
        machine = self._machine
        if machine.ack_epoch == self._acked_epoch and machine.n_reliable:
            return self._acked_through
        if self._acquire(False):
            try:
                self._acked_epoch = machine.ack_epoch
                self._acked_through = machine.acknowledged_through()
            finally:
                self._release()
        return self._acked_through

    def latest_undeliverable(self) -> bool:
        """True when a reliable reader can never get the last sample written (it expired before
        being acknowledged). The robot's local cache then forgets its last value, so the next
        reading is sent even if equal."""
        with self._lock:
            return self._machine.latest_undeliverable()

    @property
    def matched_count(self) -> int:
        with self._lock:
            return len(self._machine.proxies)

    @property
    def awaited_count(self) -> int:
        """Readers whose session was lost and whose match resumes if they come back within
        arpz.core.protocol AWAY_RETENTION_S: what is written now still reaches them, or is reported
        lost to them, when they are back."""
        with self._lock:
            return self._machine.awaited_count

    def stats(self) -> WriterStats:
        with self._lock:
            stats = self._machine.stats()
        return self._with_counters(stats)

    def close(self) -> None:
        """Send the open batch, then stop (as ``Endpoint.close``)."""
        if not self._closed:
            self.flush()
        super().close()

    def _on_close(self) -> None:
        self._publisher.undeclare()
