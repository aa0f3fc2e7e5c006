"""``Reader``: the subscribing end of a reliable channel over any ``Transport``."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from arpz.channel._channel import Channel, Endpoint
from arpz.core.protocol._common import new_guid
from arpz.core.protocol.events import DataInfo, ReaderEventCallbacks
from arpz.core.protocol.qos import QosProfile
from arpz.core.protocol.reader_machine import (
    DEFAULT_MAX_ASSEMBLY_BYTES,
    DEFAULT_MAX_SAMPLE_BYTES,
    DEFAULT_MAX_WRITERS,
    ReaderMachine,
    ReaderStats,
)
from arpz.core.protocol.timers import Clock, SystemClock
from arpz.core.transport import Transport


class Reader(Endpoint):
    """Receives from every writer whose key matches ``key_expr`` (wildcards allowed: one reader
    on ``arpz/f/robot/*/sensor/*`` serves a whole fleet). ``on_data(payload, info)`` runs on the
    reader's own threads, one call at a time, in seq order per writer, never twice for one
    sample: its delivery thread (which pulls the data from a Zenoh FIFO, no Python callback on
    Zenoh's thread) or, for samples recovered by NACK, its control thread, in turn.

    ``inline_delivery=True`` trades the own threads for latency: samples are processed and
    ``on_data`` runs on the transport's thread (no thread wake-up: usually about 1.2x raw Zenoh's
    round trip against 1.25x, see benchmarks/RESULTS.md). Only for callbacks that return quickly;
    timers and events still run on the control thread.

    ``on_data_run(key, payloads)``, when given, takes every delivery instead of ``on_data``
    (which may then be None): a whole in-order run of one writer's samples at once (a batch the
    writer sent), without a ``DataInfo`` per sample. For a consumer that needs neither seq,
    stamp nor writer, such as the CEDDP's ingest (``benchmarks/ceddp_ingest.py``, issue 17).

    A sample its writer sent as fragments (longer than the writer's ``fragment_bytes``) is
    reassembled here and delivered whole, once, like any other; the reader asks for the
    fragments it misses only. ``max_sample_bytes``: a longer sample is refused and counted
    lost (``ReaderStats.samples_too_large``); ``max_assembly_bytes``: the most reserved at once
    for samples in assembly, over all writers (a fragment beyond it waits to be resent)."""

    def __init__(
        self,
        transport: Transport,
        key_expr: str,
        qos: QosProfile,
        on_data: Callable[[bytes, DataInfo], None] | None,
        *,
        events: ReaderEventCallbacks | None = None,
        clock: Clock | None = None,
        inline_delivery: bool = False,
        max_writers: int = DEFAULT_MAX_WRITERS,
        on_data_run: Callable[[str, Sequence[bytes]], None] | None = None,
        max_sample_bytes: int = DEFAULT_MAX_SAMPLE_BYTES,
        max_assembly_bytes: int = DEFAULT_MAX_ASSEMBLY_BYTES,
    ) -> None:
        if on_data is None and on_data_run is None:
            raise ValueError("a Reader needs on_data or on_data_run")
        self.key_expr = key_expr
        self._machine = ReaderMachine(
            key_expr,
            qos,
            new_guid(),
            clock or SystemClock(),
            max_writers=max_writers,
            max_sample_bytes=max_sample_bytes,
            max_assembly_bytes=max_assembly_bytes,
        )
        self.guid = self._machine.hex
        self._channel = Channel(
            transport,
            self._machine,
            events or ReaderEventCallbacks(),
            on_data,
            f"arpz-reader-{key_expr}",
            inline=inline_delivery,
            on_data_run=on_data_run,
        )
        self._channel.start()

    @property
    def matched_count(self) -> int:
        with self._channel.lock:
            return len(self._machine.writers)

    @property
    def delivery_idle_s(self) -> float:
        """Seconds the delivery thread has waited for data since it started (0 when inline):
        one minus its growth over an interval's length is how busy the reader kept it."""
        return self._channel.delivery_wait.waited_s

    def take_backlog_ms(self) -> float | None:
        """The longest a sample waited in the transport's queue before the delivery thread took
        it, since the previous call, ms (0: none waited, or inline delivery; None: samples
        waited but the transport could not tell how long): the reader's backlog in time.
        Across a router the wait counts from the router's receipt."""
        taken = self._channel.delivery_backlog.take_max_ns()
        return None if taken is None else taken / 1e6

    @property
    def worst_backlog_ms(self) -> float | None:
        """The longest such wait since the reader started, ms (None as above)."""
        worst = self._channel.delivery_backlog.worst_known_ns
        return None if worst is None else worst / 1e6

    def backlog_ms_quantiles(self, *qs: float) -> list[float | None]:
        """Percentiles of every wait the delivery thread observed since it started, ms: the
        oldest waiting sample's wait at each pull that found the queue non-empty (None: no
        such pull, or none the transport could time)."""
        return self._channel.delivery_backlog.quantiles_ms(*qs)

    def sojourn_ms_quantiles(self, *qs: float) -> list[float | None]:
        """Percentiles over every delivered sample of its time in this process, from the
        transport's receipt to the end of its delivery pass, ms (an upper bound per sample:
        arpz.core.protocol.timers.SojournMeter; None: none measured, or inline delivery)."""
        return self._channel.delivery_sojourn.quantiles_ms(*qs)

    @property
    def worst_sojourn_ms(self) -> float | None:
        """The longest such time since the reader started, ms (None as above)."""
        return self._channel.delivery_sojourn.worst_ms

    @property
    def sojourn_untimed(self) -> int:
        """Messages delivered whose time in this process could not be told (no router
        timestamp): in no sojourn figure, counted here."""
        return self._channel.delivery_sojourn.unknown_samples

    def retune(self, *, depth: int) -> None:
        """Follow a QoS assignment's depth (as ``Writer.retune`` on the writers' side)."""
        with self._channel.lock:
            self._machine.retune(depth=depth)

    @property
    def qos(self) -> QosProfile:
        """The QoS in force: the machine's, which ``retune`` changes (the one place it lives)."""
        return self._machine.qos

    def accounted(self) -> dict[str, tuple[int, int, int, int, int]]:
        """Per matched writer: (first seq of the match, last seq accounted for, delivered, lost,
        lifespan expired)."""
        with self._channel.lock:
            return self._machine.accounted()

    def round_trips(self) -> dict[str, float]:
        """Per matched writer's topic key: the measured NACK -> resend round trip (s)."""
        with self._channel.lock:
            return self._machine.round_trips()

    def plain_samples(self) -> dict[str, int]:
        """Plain Zenoh samples (no channel header) refused so far, per key: each such key has a
        publisher that offers no channel (reported once as INCOMPATIBLE_QOS)."""
        with self._channel.lock:
            return dict(self._machine.plain_samples)

    def stats(self) -> ReaderStats:
        with self._channel.lock:
            stats = self._machine.stats()
        return self._with_counters(stats)
