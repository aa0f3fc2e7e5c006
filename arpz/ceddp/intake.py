"""The CEDDP's sensor path: the robots' samples into ``Ingest``, by one of two roads.

Through the reliable channel (``reliability = "channel"``), one wildcard ``Reader`` delivers the
samples in order per writer on its own thread and reports what it lost, what was held back
unchanged and which peers disagree on the mode. Raw (``"none"``), the samples wait in a
Zenoh-owned FIFO of ``ingest_queue_limit`` (no Python callback per sample); when it is full
Zenoh stops reading the link and the robots' publishers (congestion control BLOCK) wait, so a
slow CEDDP delays samples but never drops them. The ingest worker pulls them in batches;
"arrival" is when it takes a sample, so the latency figure includes any wait in the CEDDP.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence

from arpz.ceddp.control import ControlWorker, EventSink
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.planner import Planner
from arpz.channel import (
    PLAIN_PEER,
    FrameInfo,
    FrameReader,
    IncompatibleQosStatus,
    MessageLostStatus,
    QosPolicyKind,
    Reader,
    ReaderEventCallbacks,
    UnchangedStatus,
)
from arpz.core import keys
from arpz.core.config import LARGE_SAMPLE_BYTES, CeddpConfig
from arpz.core.protocol.timers import WaitMeter
from arpz.core.transport import PullSubscriber, Transport

log = logging.getLogger(__name__)

#: samples the raw ingest worker takes from the FIFO at most per pass
_RAW_BATCH = 2000
#: channel samples ingested under one hold of the ingest lock (``_on_channel_run``)
_RUN_CHUNK = 8
#: a hold of the ingest lock longer than this takes the next chunks down to one sample a hold
_RUN_HOLD_NS = 1_000_000


class SensorIntake:
    """Thread: the Reader's own threads (channel) or ``run_raw`` (``arpz-ingest``, raw) call
    ``Ingest`` under its lock."""

    def __init__(
        self,
        config: CeddpConfig,
        transport: Transport,
        ingest: Ingest,
        fanout: Planner,
        control: ControlWorker,
        event: EventSink,
    ) -> None:
        self.config = config
        self.transport = transport
        self.ingest = ingest
        #: every planner at once (the server's fan-out)
        self.fanout = fanout
        self.control = control
        self._event = event
        self.reader: Reader | None = None
        #: camera frames and point clouds (``frames/{topic}``), reassembled from fragments
        self.frames: FrameReader | None = None
        self.raw: PullSubscriber | None = None
        self.processed = 0
        #: samples of a channel run per hold of the ingest lock (``_on_channel_run``)
        self._run_chunk = _RUN_CHUNK
        #: samples the reliable channel reported irrecoverably lost (GAP, timeout, writer gone)
        self.channel_lost = 0
        #: raw path: channel-headed sensor samples refused per (robot, topic) (INCOMPATIBLE_QOS)
        self.raw_refused: dict[tuple[str, str], int] = {}
        #: raw path: how long the ingest worker waited for samples (see ``idle_s``)
        self._raw_wait = WaitMeter()
        self._wake_key = keys.sensor_key(config.fleet, "ceddp-wake", "wake")
        self._stopping = threading.Event()

    def open(self) -> None:
        cfg = self.config
        sensor_qos = cfg.profile("sensor")
        expr = keys.all_sensors(cfg.fleet, cfg.partition)
        if sensor_qos is None:
            self.raw = self.transport.subscribe_pull(expr, cfg.ingest_queue_limit)
            return
        self.reader = Reader(
            self.transport,
            expr,
            sensor_qos,
            None,
            on_data_run=self._on_channel_run,
            events=ReaderEventCallbacks(
                message_lost=self._on_channel_lost,
                unchanged=self._on_channel_unchanged,
                incompatible_qos=self._on_incompatible,
            ),
            max_writers=cfg.max_robots * cfg.max_topics_per_robot,
        )
        frames_qos = cfg.profile("frames")
        assert frames_qos is not None, "channel mode has every profile"
        self.frames = FrameReader(
            self.transport,
            keys.all_frames(cfg.fleet, cfg.partition),
            frames_qos,
            self._on_frame,
            max_frame_bytes=LARGE_SAMPLE_BYTES,
            events=ReaderEventCallbacks(incompatible_qos=self._on_incompatible),
        )
        self.control.sensor_reader = self.reader

    def stop(self) -> None:
        """Stop taking samples: what is already queued is ingested first (raw: the wake sample
        queues behind everything received)."""
        self._stopping.set()
        if self.raw is not None:
            self.transport.put(self._wake_key, b"")
        if self.reader is not None:
            self.reader.close()
        if self.frames is not None:
            self.frames.close()

    def idle_s(self) -> float:
        """Seconds the sensor path's thread has waited for samples so far; the rest of its time
        it worked (or waited for a CPU): what the overload governor reads as the CEDDP's load."""
        if self.reader is not None:
            return self.reader.delivery_idle_s
        return self._raw_wait.waited_s

    def take_backlog_ms(self) -> float | None:
        """The longest a sample waited between the router's receipt and the sensor path taking
        it, since the previous call, ms (the metrics interval); None on the raw path, which
        does not measure it, or when the samples carried no router timestamp."""
        return self.reader.take_backlog_ms() if self.reader is not None else None

    def worst_backlog_ms(self) -> float | None:
        """The longest such wait since start, ms (None on the raw path)."""
        return self.reader.worst_backlog_ms if self.reader is not None else None

    def backlog_ms_quantiles(self, *qs: float) -> list[float | None]:
        """Percentiles of those waits since start, ms (None on the raw path, or none timed)."""
        if self.reader is None:
            return [None] * len(qs)
        return self.reader.backlog_ms_quantiles(*qs)

    def sojourn_ms(self) -> dict[str, float | int | None]:
        """The samples' time inside the CEDDP, from the router's receipt to the end of the
        sensor path's pass that processed them, ms: p50, p99 and max over the run (upper
        bounds, arpz.core.protocol.timers.SojournMeter; None on the raw path, or none measured)."""
        if self.reader is None:
            return {
                "sojourn_ms_p50": None,
                "sojourn_ms_p99": None,
                "sojourn_ms_max": None,
                "sojourn_untimed": None,
            }
        p50, p99 = self.reader.sojourn_ms_quantiles(50, 99)
        return {
            "sojourn_ms_p50": p50,
            "sojourn_ms_p99": p99,
            "sojourn_ms_max": self.reader.worst_sojourn_ms,
            # messages without a router timestamp: in none of the figures above
            "sojourn_untimed": self.reader.sojourn_untimed,
        }

    def refused(self) -> dict[str, int]:
        """Samples refused for the mode, per robot key (channel: plain puts; raw: headed)."""
        if self.reader is not None:
            return self.reader.plain_samples()
        with self.ingest.lock:  # the raw ingest worker adds to it under this lock
            raw = list(self.raw_refused.items())
        return {keys.sensor_key(self.config.fleet, r, t): n for (r, t), n in raw}

    def run_raw(self) -> None:
        """The raw ingest worker: pull in batches; block in ``recv`` (no GIL held) when there
        are none."""
        sensors, ingest, stopping, wake = self.raw, self.ingest, self._stopping, self._wake_key
        assert sensors is not None, "open() declares the subscriber before the worker runs"
        try_recv, wait = sensors.try_recv, self._raw_wait
        while True:
            item = try_recv()
            if item is None:
                wait.start()
                try:
                    item = sensors.recv()
                finally:
                    wait.stop()
            batch = [item]
            while len(batch) < _RAW_BATCH and (item := try_recv()) is not None:
                batch.append(item)
            arrival_ns = time.time_ns()
            with ingest.lock:
                for key, payload, att in batch:
                    if key == wake and stopping.is_set():
                        return
                    if att is not None:
                        self._refuse_channel_sample(key)
                        continue
                    try:
                        ingest.handle_sensor(key, payload, arrival_ns)
                    except Exception:  # a bad sample or a planner bug must not stop the CEDDP
                        log.exception("ingest failed on %s", key)
                self.processed += len(batch)

    def _on_channel_run(self, key: str, payloads: Sequence[bytes]) -> None:
        """Samples of one writer delivered by the reliable channel (a batch), in order, on its
        worker: a chunk at a time under one hold of the ingest lock and one arrival time, the
        topic looked up once a chunk. A call per sample, with its ``DataInfo``, lock and clock
        read, cost 1.4-1.7x the CPU a sample (``python benchmarks/investigations/ingest_cost.py``;
        issue 17).

        Chunks of ``_RUN_CHUNK``, down to one sample while a hold takes longer than
        ``_RUN_HOLD_NS``: the lock also serves the control worker (joins, clock replies, QoS)
        and the overload governor, and a slow planner (``[overload] planner_cost_us``, 10 ms a
        reading in test_overload) held it for a whole chunk's readings at a time; a whole run
        per hold failed that test at stop 26, chunks of 8 without the bound at this one."""
        ingest = self.ingest
        start, end = 0, len(payloads)
        while start < end:
            chunk = payloads[start : start + self._run_chunk]
            with ingest.lock:
                arrival_ns = time.time_ns()
                ingest.handle_run(key, chunk, arrival_ns)
                self.processed += len(chunk)
                held_ns = time.time_ns() - arrival_ns
            start += len(chunk)
            # what a whole chunk would hold the lock for at this pace decides the next chunk
            pace_ns = held_ns * _RUN_CHUNK // len(chunk)
            self._run_chunk = _RUN_CHUNK if pace_ns <= _RUN_HOLD_NS else 1

    def _ingest_one(self, key: str, payload: bytes, *, large: bool) -> None:
        with self.ingest.lock:
            try:
                self.ingest.handle_sensor(key, payload, time.time_ns(), large=large)
            except Exception:  # a bad sample or a planner bug must not stop the CEDDP
                log.exception("ingest failed on %s", key)
            self.processed += 1

    def _on_frame(self, payload: bytes, info: FrameInfo) -> None:
        """A camera frame or point cloud, reassembled: a ``Sample`` like any sensor's, ingested
        under its ``sensor/{topic}`` key (the FrameReader bounded its size already)."""
        parsed = keys.parse_robot_key(info.key)
        if parsed is None or parsed[1] != "frames":
            with self.ingest.lock:
                self.ingest.counters.unknown_keys += 1
            return
        self._ingest_one(
            keys.sensor_key(self.config.fleet, parsed[0], parsed[2]), payload, large=True
        )

    def _refuse_channel_sample(self, key: str) -> None:
        """Raw path (``reliability = "none"``): a sample with a channel header comes from a robot
        in channel mode. Refused and counted, so the pair's disagreement is never silent."""
        parsed = keys.parse_robot_key(key)
        if parsed is None:
            self.ingest.counters.unknown_keys += 1
            return
        slot = (parsed[0], parsed[2])
        seen = self.raw_refused.get(slot, 0)
        if not seen and len(self.raw_refused) >= self.config.max_robots * 4:
            self.ingest.counters.over_limit += 1
            return
        self.raw_refused[slot] = seen + 1
        if not seen:
            self.control.on_incompatible(key, QosPolicyKind.RELIABILITY)

    def _on_incompatible(self, status: IncompatibleQosStatus) -> None:
        """The sensor reader refused a writer or plain puts (``plain:{key}``): tell the control
        worker, which marks the robot INCOMPATIBLE_QOS."""
        key = status.peer[len(PLAIN_PEER) :] if status.peer.startswith(PLAIN_PEER) else ""
        if not key:
            self._event(
                f"reliable channel: incompatible QoS ({status.last_policy_kind.value}) with "
                f"writer {status.peer}",
                "ERROR",
            )
            return
        self.control.on_incompatible(key, status.last_policy_kind)

    def _on_channel_unchanged(self, status: UnchangedStatus) -> None:
        """A robot's local cache held a repeat back: planners judging freshness must know."""
        if not self.fanout.wants_unchanged:
            return
        parsed = keys.parse_robot_key(status.key)
        if parsed is not None and parsed[1] == "sensor":
            self.fanout.on_unchanged(parsed[0], parsed[2], status.stamp_ns)

    def _on_channel_lost(self, status: MessageLostStatus) -> None:
        self.channel_lost += status.total_count_change
