"""The CEDDP's Rerun dashboard: the only module of arpz that imports rerun.

The server hands frames and events to ``Dashboard.submit``, which never blocks: a bounded queue
feeds one logging thread, and a frame that finds the queue full is dropped and counted (Rerun
logging costs about 50 us a call, and must never slow down a Zenoh callback or the ingest).
Entity paths put the metric first (``/metrics/{metric}/{robot}/{topic}``) so that the one
time-series view per metric in the blueprint picks up new robots and topics by itself.

Sinks: always a FileSink (the ``.rrd``), optionally a GrpcServerSink with a memory limit that a
viewer can connect to; never a client-side gRPC sink, which blocks forever when no viewer runs.
"""

from __future__ import annotations

import itertools
import logging
import math
import queue
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Any, cast

import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb

from arpz.ceddp.pacing import Pacer
from arpz.core.errors import ConfigError
from arpz.core.frames import ROBOT_METRICS, TIMELINE, TOPIC_METRICS, Event, MetricsFrame, WorldMap
from arpz.core.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
throttled = ThrottledLog(log)


#: the robots' sensor health (issue 41), beside ``ROBOT_METRICS``: one series per robot
HEALTH_METRICS: dict[str, str] = {
    "driver_errors": "sensor driver errors: reads that gave no reading (cumulative)",
    "silent_sensors": "sensors with no reading for the robot's last report interval",
    "duplicate_processes": "other processes running with the robot's id (samples dropped)",
}


def blueprint() -> rrb.Blueprint:
    views: list[rrb.View] = [
        rrb.TimeSeriesView(origin=f"/metrics/{name}", name=title)
        for name, title in {**TOPIC_METRICS, **ROBOT_METRICS, **HEALTH_METRICS}.items()
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Grid(*views),
                rrb.TextLogView(origin="/events", name="fleet events"),
                row_shares=[4, 1],
            ),
            rrb.Spatial2DView(origin="/world", name="world (missions)"),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


_TIMEOUT = object()

#: the one column of a Scalars archetype, as a template: its descriptor and its Arrow type
(_SCALARS,) = rr.Scalars.columns(scalars=np.zeros(1))
_SCALARS_DESCRIPTOR = _SCALARS.component_descriptor()
_SCALARS_TYPE = _SCALARS.as_arrow_array().type


class _Column:
    """A column already in Arrow form, for ``send_columns``: what ``rr.TimeColumn`` and Rerun's
    component columns hand it (a name or descriptor, and an Arrow array), without their
    conversion from Python. Not ``rr.ComponentColumn``: it partitions its batch again into
    unit-length rows, a cost a series the flush is rid of."""

    def __init__(self, name: Any, array: pa.Array) -> None:
        self._name = name
        self._array = array

    def timeline_name(self) -> Any:
        return self._name

    def component_descriptor(self) -> Any:
        return self._name

    def as_arrow_array(self) -> pa.Array:
        return self._array


ROBOT_COLOURS = [(230, 80, 60), (60, 140, 230), (60, 190, 90), (200, 160, 40), (160, 90, 200)]


class Dashboard:
    def __init__(
        self,
        rrd_path: str | Path,
        *,
        grpc_port: int = 0,
        recording_id: str | None = None,
        queue_limit: int = 10_000,
        flush_period_s: float = 5.0,
    ) -> None:
        self.rrd_path = Path(rrd_path)
        self.rrd_path.parent.mkdir(parents=True, exist_ok=True)
        self.previous = preserve_previous(self.rrd_path)
        self.dropped = 0
        self.logged_rows = 0
        #: metric rows not logged: a value that was not a number, or a flush Rerun failed
        self.rows_refused = 0
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=queue_limit)
        #: metric rows waiting to be sent as columns: entity path -> (timestamps_s, values)
        self._pending: dict[str, tuple[list[float], list[float]]] = {}
        self._flush_period_s = flush_period_s
        # The first flush comes half a period after start: the CEDDP persists its summary every
        # summary_period_s (5 s) from its start too, and the two paced loops at once shared the
        # GIL the sensor path waits for (samples 20-30 ms late after each, at 50 robots; apart,
        # about 15 ms and fewer: issue 17, stop 36)
        self._last_flush = time.monotonic() - flush_period_s / 2
        self._rec = rr.RecordingStream("arpz-ceddp", recording_id=recording_id)
        sinks: list[rr.FileSink | rr.GrpcServerSink] = [rr.FileSink(str(self.rrd_path))]
        if grpc_port:
            sinks.append(
                rr.GrpcServerSink(bind_ip="0.0.0.0", port=grpc_port, server_memory_limit="256MB")
            )
        self._rec.set_sinks(*sinks, default_blueprint=blueprint())
        self._thread = threading.Thread(target=self._run, name="arpz-dashboard", daemon=True)
        self._thread.start()
        self._closed = False

    def submit(self, item: MetricsFrame | Event | WorldMap | Any) -> bool:
        """Queue an item for logging; False (and counted) if the queue is full."""
        try:
            self._queue.put_nowait(item)
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def _run(self) -> None:
        rec = self._rec
        while True:
            try:
                due_s = self._last_flush + self._flush_period_s - time.monotonic()
                item = self._queue.get(timeout=max(0.0, due_s))
            except queue.Empty:
                item = _TIMEOUT
            if item is None or time.monotonic() - self._last_flush >= self._flush_period_s:
                self._flush_metrics()
            if item is None:
                return
            if item is _TIMEOUT:
                continue
            try:
                rec.set_time(TIMELINE, timestamp=item.stamp_ns / 1e9)
                if isinstance(item, Event):
                    rec.log("/events", rr.TextLog(item.text, level=item.level))
                    continue
                if isinstance(item, WorldMap):
                    rec.log(
                        "/world/walls",
                        rr.LineStrips2D(item.walls, colors=(90, 90, 90)),
                        static=True,
                    )
                    if item.obstacles:
                        closed = [[*o, o[0]] for o in item.obstacles]
                        rec.log(
                            "/world/obstacles",
                            rr.LineStrips2D(closed, colors=(200, 0, 0)),
                            static=True,
                        )
                    continue
                if not isinstance(item, MetricsFrame):
                    self._log_world(item)
                    continue
                t_s = item.stamp_ns / 1e9
                pace = Pacer()  # a frame has a row per topic: the sensor path goes first
                for (robot, topic), metrics in item.topics.items():
                    pace()
                    for name, value in metrics.items():
                        self._add(f"/metrics/{name}/{_part(robot)}/{_part(topic)}", t_s, value)
                for robot, metrics in item.robots.items():
                    for name, value in metrics.items():
                        self._add(f"/metrics/{name}/{_part(robot)}", t_s, value)
            except Exception:  # a Rerun failure must not kill the server's reporting
                log.exception("Rerun logging failed")

    def _add(self, path: str, t_s: float, value: float) -> None:
        """A bad value (not a number) is refused here, counted and logged; the frame's other
        values go on (a bad one must never reach the flush, which builds one array of all)."""
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.rows_refused += 1
            throttled.warning(path, "dashboard: %s is not a number: %r (not logged)", path, value)
            return
        times, values = self._pending.setdefault(path, ([], []))
        times.append(t_s)
        values.append(number)

    def _flush_metrics(self) -> None:
        """Send every series' pending rows as one column chunk. One ``rr.log`` per value made a
        chunk per value (about 1 KB each in the file and in memory, measured by the soak test);
        columns of a few seconds cost tens of bytes a value.

        The arrays of all series are built once and each series sends a zero-copy slice of
        them: 43 us a series, against 208 through Rerun's own column builders (``rr.TimeColumn``,
        ``rr.Scalars.columns``; ``python benchmarks/investigations/metrics_cost.py``). A fleet of
        25 robots
        has about 2 400 series; with the builders its flush was a quarter of an idle CEDDP's
        Python time (a py-spy profile, benchmarks/RESULTS.md, issue 17)."""
        self._last_flush = time.monotonic()
        pending, self._pending = self._pending, {}
        if not pending:
            return
        lengths = [len(times) for times, _ in pending.values()]
        total = sum(lengths)
        try:  # on the dashboard's thread, outside ``_run``'s per-item guard
            times = np.fromiter(
                itertools.chain.from_iterable(t for t, _ in pending.values()), float, total
            )
            values = np.fromiter(
                itertools.chain.from_iterable(v for _, v in pending.values()), float, total
            )
            stamps = pa.array((times * 1e9).astype("datetime64[ns]"), pa.timestamp("ns"))
            scalars = pa.ListArray.from_arrays(
                pa.array(np.arange(total + 1, dtype=np.int32)),
                pa.array(values, pa.float64()),
                type=_SCALARS_TYPE,
            )
        except Exception:
            self.rows_refused += total
            log.exception("Rerun logging failed: %d metric rows not logged", total)
            return
        start = 0
        pace = Pacer()  # thousands of series at 50 robots: the sensor path goes first
        for path, length in zip(pending, lengths, strict=True):
            pace()
            try:
                scalar_column = _Column(_SCALARS_DESCRIPTOR, scalars.slice(start, length))
                self._rec.send_columns(
                    path,
                    indexes=[_Column(TIMELINE, stamps.slice(start, length))],
                    # send_columns types this as Rerun's ComponentColumn; it calls only the two
                    # methods _Column has (rerun 0.41, pinned in pyproject.toml)
                    columns=[cast(Any, scalar_column)],
                )
                self.logged_rows += length
            except Exception:
                self.rows_refused += length
                log.exception("Rerun logging failed for %s", path)
            start += length

    def _log_world(self, view: Any) -> None:
        """A ``WorldView`` of arpz.ceddp.mission: poses, rays and paths per robot."""
        rec = self._rec
        for index, (robot, (x, y, theta)) in enumerate(sorted(view.poses.items())):
            colour = ROBOT_COLOURS[index % len(ROBOT_COLOURS)]
            part = _part(robot)
            rec.log(
                f"/world/robots/{part}",
                rr.Points2D([(x, y)], radii=0.2, colors=colour, labels=robot),
            )
            rec.log(
                f"/world/heading/{part}",
                rr.Arrows2D(
                    origins=[(x, y)],
                    vectors=[(0.6 * math.cos(theta), 0.6 * math.sin(theta))],
                    colors=colour,
                ),
            )
            if robot in view.rays:
                rec.log(
                    f"/world/rays/{part}",
                    rr.LineStrips2D(
                        [[(x, y), end] for end in view.rays[robot]], colors=(*colour, 90)
                    ),
                )
            if view.paths.get(robot):
                rec.log(f"/world/paths/{part}", rr.LineStrips2D([view.paths[robot]], colors=colour))

    def close(self) -> None:
        """Log what is queued, then flush and close the file so it is valid."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._thread.join(timeout=30)
        self._rec.flush()
        self._rec.disconnect()


def preserve_previous(path: Path) -> Path | None:
    """Never overwrite an earlier run's recording: move it aside and, if its writer was killed
    before it could write the footer (SIGKILL, power loss), repair it with ``rerun rrd optimize``
    so it verifies and opens. Returns where it went, or None if there was none."""
    if not path.exists():
        return None
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(path.stat().st_mtime))
    kept = path.with_name(f"{path.stem}.{stamp}{path.suffix}")
    counter = 1
    while kept.exists():
        kept = path.with_name(f"{path.stem}.{stamp}-{counter}{path.suffix}")
        counter += 1
    path.rename(kept)
    rerun_cli = [sys.executable, "-m", "rerun", "rrd"]
    verify = subprocess.run([*rerun_cli, "verify", str(kept)], capture_output=True, timeout=120)
    if verify.returncode != 0:
        repaired = kept.with_name(kept.name + ".repairing")
        fix = subprocess.run(
            [*rerun_cli, "optimize", str(kept), "-o", str(repaired)],
            capture_output=True,
            timeout=600,
        )
        if fix.returncode == 0 and repaired.exists():
            repaired.replace(kept)
            log.warning("the previous recording had no footer (killed?): repaired as %s", kept)
        else:
            repaired.unlink(missing_ok=True)
            log.error("the previous recording %s is damaged and could not be repaired", kept)
    else:
        log.info("the previous recording was kept as %s", kept)
    return kept


def rrd_recording_ids(path: Path) -> list[str]:
    """The recording ids in an ``.rrd`` (one per CEDDP run merged into it)."""
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        # a CEDDP killed hard leaves no footer; the file still reads by scanning it
        warnings.simplefilter("ignore")
        return [e.recording_id for e in RrdReader(str(path)).recordings()]


def serve_web_viewer(web_port: int) -> None:
    """Serve Rerun's web viewer (from the rerun-sdk wheel, on every interface) on ``web_port``
    (``rerun_web_port``): a browser opening it with ``?url=rerun+http://HOST:GRPC_PORT/proxy``
    shows the live recording of the dashboard's gRPC server (``grpc_port``). The status page
    builds that link. The viewer runs until the process exits; a port in use is a ConfigError
    naming the setting."""
    try:
        rr.serve_web_viewer(web_port=web_port, open_browser=False)
    except RuntimeError as exc:
        raise ConfigError(
            f"rerun_web_port {web_port} cannot be served: {exc}; choose another rerun_web_port "
            "(or 0 to turn the Rerun web viewer off)"
        ) from None


def merge_rrd(files: list[Path], merged: Path, *, timeout_s: float) -> str | None:
    """``rerun rrd merge`` of ``files`` into ``merged``; None, or why it failed."""
    result = subprocess.run(
        [sys.executable, "-m", "rerun", "rrd", "merge", *map(str, files), "-o", str(merged)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )
    if result.returncode != 0 or not merged.exists():
        return f"rerun rrd merge failed: {result.stderr[-500:]}"
    return None


def _part(name: str) -> str:
    return str(rr.escape_entity_path_part(name))
