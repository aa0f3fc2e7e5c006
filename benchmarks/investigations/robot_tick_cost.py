"""CPU cost of one robot tick on the sensing thread: the real sensor path (simulated drivers,
local cache, sample encoding, one reliable-channel ``Writer`` per topic, the tick's bundle)
against the floor, a plain Zenoh put of the same tick's bundle, in one run.

This is the load generator's cost in ``python -m arpz.perf fleet`` (issue 17): there the robots
spend about twice the CEDDP's CPU a sample, so on one 2-core host they, not the server, end the
scaling curve. A router process and a reader process (``READER`` below: an arpz ``Reader`` on
``.../sensor/*`` as the CEDDP's, so acknowledgements flow back and nothing of the reader's own
cost is in this process) run on loopback;
this process builds one robot's sensors as ``RobotAgent`` does (``build_sensors`` behind a
``Bundler`` sized by ``frame_fragment_bytes``, the fleet's robot config: KEEP_ALL, piggybacked
heartbeats, heartbeat backoff 8, local cache off) and runs ticks at ``--tick-hz`` (1 000 a
second; the fleet's rate is 100), reading its main thread's CPU time (``time.thread_time``):
the work of ``sense`` for every topic and of the bundle's put, not the channel's other threads.
The floor puts the bytes of one recorded bundle each tick.

    python benchmarks/investigations/robot_tick_cost.py [--ticks 5000] [--topics 8] [--rounds 3]
        [--hot]

``--hot`` runs the ticks back to back in bursts (warm caches), not paced: the sensing path's
own cost, without what the caches cost after each sleep (for an A/B of a change to it, run
from each checkout in turn: the window moves both figures).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from arpz.channel.bundling import Bundler  # noqa: E402
from arpz.core.config import RobotConfig, from_dict  # noqa: E402
from arpz.core.endpoints import frame_fragment_bytes  # noqa: E402
from arpz.core.protocol import bundle  # noqa: E402
from arpz.core.transport import SessionSettings  # noqa: E402
from arpz.perf.fleet import FleetOptions, robot_config  # noqa: E402
from arpz.perf.harness import child, free_port, perf_router  # noqa: E402
from arpz.robot.sensing import SensorChannel, build_sensors, sense  # noqa: E402
from arpz.transport.zenoh import ZenohTransport  # noqa: E402

ROBOT = "r001"
READER = """
import sys, threading
from arpz.core.protocol.qos import QosProfile, HistoryPolicy
from arpz.channel import Reader
from arpz.core.transport import SessionSettings
from arpz.transport.zenoh import ZenohTransport
transport = ZenohTransport.open(SessionSettings(mode="client", connect=[sys.argv[1]]))
reader = Reader(transport, sys.argv[2], QosProfile(history=HistoryPolicy.KEEP_ALL), None,
                on_data_run=lambda key, payloads: None)
floor = transport.subscribe("arpz/perf/floor/**", lambda key, payload, attachment: None)
print("ready", file=sys.stderr, flush=True)
threading.Event().wait()  # until the benchmark terminates it
"""
RATE_HZ = 100.0
#: ``--hot``: ticks a burst, and the pause after each
HOT_BURST = 300
HOT_PAUSE_S = 0.05


class _Capturing:
    """The robot's transport, noting the last bundle it put while ``recording`` (the warm-up):
    the floor then puts those very bytes. Off, it costs one attribute test a bundle."""

    def __init__(self, inner: ZenohTransport) -> None:
        self.inner = inner
        self.recording = True
        self.last: tuple[bytes, bytes | None] = (b"", None)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def publisher(self, key: str, **options: Any) -> Any:
        inner = self.inner.publisher(key, **options)
        capture = self

        class Noting:
            matching = property(lambda _self: inner.matching)

            def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
                if capture.recording and key.endswith(bundle.CHUNK):
                    capture.last = (payload, attachment)
                inner.put(payload, attachment=attachment)

            def undeclare(self) -> None:
                inner.undeclare()

        return Noting()


def robot_sensors(
    transport: _Capturing, endpoint: str, topics: int, base: Path
) -> tuple[Bundler, list[SensorChannel]]:
    options = FleetOptions(robots=1, topics=topics, rate_hz=RATE_HZ)
    config = from_dict(robot_config(options, ROBOT, endpoint, 1), RobotConfig, source="bench")
    max_bytes = config.frame_fragment_bytes or frame_fragment_bytes(config.connect)
    bundler = Bundler(transport, max_bytes=max_bytes)  # type: ignore[arg-type]
    sensors = build_sensors(config, bundler, None, base)
    for sensor in sensors:
        sensor.wall_ns = time.time_ns
    return bundler, sensors


def run_ticks(
    bundler: Bundler, sensors: list[SensorChannel], first: int, ticks: int, tick_hz: float
) -> float:
    """Main-thread CPU us a tick, for ``ticks`` ticks from tick number ``first``, paced at
    ``tick_hz`` (the sensors' clock still advances 1/100 s a tick): flat out, the reader falls
    behind and a KEEP_ALL writer blocks, which is not the robot's cost."""
    cpu0 = time.thread_time()
    start = time.monotonic()
    for tick in range(first, first + ticks):
        now_s = tick / RATE_HZ
        with bundler.collect():
            for sensor in sensors:
                sense(sensor, now_s, ROBOT)
        ahead = start + (tick - first + 1) / tick_hz - time.monotonic()
        if ahead > 0:
            time.sleep(ahead)
    return (time.thread_time() - cpu0) / ticks * 1e6


def hot_ticks(bundler: Bundler, sensors: list[SensorChannel], first: int, ticks: int) -> float:
    """Main-thread CPU us a tick run back to back, in bursts of ``HOT_BURST`` ticks with a
    pause after each (for the reader to catch up): the median burst's figure. The code's own
    cost, with its caches warm; at 100 Hz on a shared host each tick costs up to 5x this
    (after each sleep the caches are cold): the paced figure, not this one, is a robot's.
    This one shows a change to the code itself without the cold caches' share."""
    bursts: list[float] = []
    tick = first
    while tick < first + ticks:
        cpu0 = time.thread_time()
        for _ in range(HOT_BURST):
            with bundler.collect():
                for sensor in sensors:
                    sense(sensor, tick / RATE_HZ, ROBOT)
            tick += 1
        bursts.append((time.thread_time() - cpu0) / HOT_BURST * 1e6)
        time.sleep(HOT_PAUSE_S)
    return statistics.median(bursts)


def floor_ticks(
    transport: ZenohTransport, key: str, sample: tuple[bytes, bytes | None], ticks: int
) -> float:
    publisher = transport.publisher(key)
    payload, attachment = sample
    try:
        cpu0 = time.thread_time()
        for _ in range(ticks):
            publisher.put(payload, attachment=attachment)
        return (time.thread_time() - cpu0) / ticks * 1e6
    finally:
        publisher.undeclare()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ticks", type=int, default=5000)
    ap.add_argument("--topics", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--tick-hz", type=float, default=1000.0, help="ticks a second (1000)")
    ap.add_argument(
        "--hot",
        action="store_true",
        help="ticks back to back in bursts of 300 (warm caches: the code's own cost, for A/Bs)",
    )
    args = ap.parse_args()
    if args.ticks < 1 or args.rounds < 1:
        ap.error(f"--ticks and --rounds must be >= 1, got {args.ticks} and {args.rounds}")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sensor_keys = f"arpz/perf/robot/{ROBOT}/sensor/*"
    robot_rows: list[float] = []
    floor_rows: list[float] = []
    with perf_router(endpoint), tempfile.TemporaryDirectory() as tmp:
        # the CEDDP's side of the channel, with nothing behind it: a fleet reader that counts
        reader = [sys.executable, "-c", READER, endpoint, sensor_keys]
        transport = ZenohTransport.open(SessionSettings(mode="client", connect=[endpoint]))
        try:
            with child(reader, ready="ready"):
                capturing = _Capturing(transport)
                bundler, sensors = robot_sensors(capturing, endpoint, args.topics, Path(tmp))
                outlets = [s.output for s in sensors]
                deadline = time.monotonic() + 10
                while not all(o.matched for o in outlets) and time.monotonic() < deadline:
                    time.sleep(0.01)
                # warm-up: the first ticks fill caches and match late writers
                run_ticks(bundler, sensors, 0, 200, args.tick_hz)
                capturing.recording = False
                # on a key of its own, which the reader's subscription does not cover
                floor_key = f"arpz/perf/floor/{bundle.CHUNK}"
                for tick in range(args.rounds):
                    first = 200 + tick * args.ticks
                    if args.hot:
                        robot_rows.append(hot_ticks(bundler, sensors, first, args.ticks))
                    else:
                        robot_rows.append(
                            run_ticks(bundler, sensors, first, args.ticks, args.tick_hz)
                        )
                    floor_rows.append(floor_ticks(transport, floor_key, capturing.last, args.ticks))
                    print(
                        f"round {tick + 1}/{args.rounds}: robot tick {robot_rows[-1]:7.1f} us CPU, "
                        f"floor {floor_rows[-1]:6.1f} us ({len(capturing.last[0])} B bundle)",
                        flush=True,
                    )
                for outlet in outlets:
                    outlet.close(5.0)
        finally:
            transport.close()
    robot, floor = statistics.median(robot_rows), statistics.median(floor_rows)
    print()
    print(f"| {args.topics} topics a tick | main-thread CPU us a tick | us a sample | / floor |")
    print("|---|---|---|---|")
    print(f"| robot tick (sense x {args.topics}, bundle put) | {robot:.1f} | "
          f"{robot / args.topics:.1f} | {robot / floor:.1f}x |")  # fmt: skip
    print(f"| floor: one plain put of the tick's bundle bytes | {floor:.1f} | - | 1.0x |")


if __name__ == "__main__":
    main()
