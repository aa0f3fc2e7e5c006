"""The cost of the ROS 2 bridge: the same fleet twice in one run, without and with ``[ros2]``.

A real CEDDP (the router) and real robot processes (preset machine1, ``--rate`` Hz per sensor);
in this process an arpz client reads every sensor topic through the reliable channel (the
"fleet" side: what any arpz consumer sees) and, in the run with the bridge, a plain Zenoh
subscriber on the ROS 2 domain's keys plays the ROS 2 node (what ``ros2 topic echo`` would
get). Latency is arrival minus the robot's stamp (one host, one clock): for the ROS 2 side the
stamp is the attachment's source timestamp, which the bridge sets to the robot's stamp.
Printed: samples/s and latency p50/p99 of each side, the CEDDP's own ingest latency, and the
bridge's counters.

    python benchmarks/ros2_bridge.py --robots 2 --rate 200 --duration 8
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from arpz.bridge import rmw_zenoh  # noqa: E402
from arpz.channel import DataInfo, Reader  # noqa: E402
from arpz.core import keys  # noqa: E402
from arpz.core.messages import SAMPLE_DECODER  # noqa: E402
from arpz.core.percentiles import percentile  # noqa: E402
from arpz.core.traffic import SENSOR_QOS  # noqa: E402
from tests.integration.fleet import ceddp, robots, settle, write_robot  # noqa: E402
from tests.support import client, wait_until  # noqa: E402

DOMAIN = 0


class Meter:
    """Arrivals and latencies (ms) after ``start``."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.on = False
        self.latencies: list[float] = []
        self.started = 0.0
        self.stopped = 0.0

    def add(self, stamp_ns: int) -> None:
        now = time.time_ns()
        with self.lock:
            if self.on:
                self.latencies.append((now - stamp_ns) / 1e6)

    def start(self) -> None:
        with self.lock:
            self.on, self.started = True, time.monotonic()

    def stop(self) -> dict[str, Any]:
        with self.lock:
            self.on, self.stopped = False, time.monotonic()
            values = sorted(self.latencies)
        elapsed = self.stopped - self.started
        return {
            "samples": len(values),
            "per_s": round(len(values) / elapsed, 1) if elapsed > 0 else 0.0,
            "latency_ms_p50": round(percentile(values, 50), 3) if values else None,
            "latency_ms_p99": round(percentile(values, 99), 3) if values else None,
        }


def run(tmp: Path, args: argparse.Namespace, *, bridge: bool) -> dict[str, Any]:
    extra = f"[ros2]\nenabled = true\ndomain_id = {DOMAIN}\n" if bridge else ""
    with ceddp(tmp, extra=extra) as (server, endpoint):
        configs = [
            # every reading sent (no local cache: it holds unchanged readings back), so that the
            # offered rate is what goes through; the line lands in write_robot's [local_cache]
            write_robot(
                tmp,
                f"robot{i}",
                endpoint,
                preset="machine1",
                rate_hz=args.rate,
                extra="enabled = false\n",
            )
            for i in range(1, args.robots + 1)
        ]
        with robots(tmp, configs), client(endpoint) as transport:
            fleet, ros = Meter(), Meter()

            def on_sample(payload: bytes, info: DataInfo) -> None:
                fleet.add(SAMPLE_DECODER.decode(payload).stamp_ns)

            def on_ros(key: str, payload: bytes, attachment: bytes | None) -> None:
                if attachment is not None:
                    ros.add(rmw_zenoh.parse_attachment(attachment).source_timestamp_ns)

            reader = Reader(transport, keys.all_sensors("itest"), SENSOR_QOS, on_sample)
            transport.subscribe(f"{DOMAIN}/**", on_ros)
            wait_until(lambda: reader.matched_count >= args.robots, timeout_s=20, what="robots")
            settle(2.0)  # discovery, announcements, the bridge's publishers
            fleet.start()
            ros.start()
            settle(args.duration)
            result: dict[str, Any] = {"fleet_side": fleet.stop(), "bridge": bridge}
            if bridge:
                result["ros2_side"] = ros.stop()
            reader.close()
        assert server.interrupt() == 0
    summary = json.loads((tmp / "summary.json").read_text())
    result["ceddp_latency_ms_p50"] = {
        name: None if r["latency_ms_p50"] is None else round(r["latency_ms_p50"], 3)
        for name, r in sorted(summary["robots"].items())
    }
    if bridge:
        result["bridge_counters"] = summary["ros2"]["counters"]
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--robots", type=int, default=2)
    parser.add_argument("--rate", type=float, default=200.0, help="Hz per sensor (machine1: 6)")
    parser.add_argument("--duration", type=float, default=8.0)
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as a, tempfile.TemporaryDirectory() as b:
        without = run(Path(a), args, bridge=False)
        with_bridge = run(Path(b), args, bridge=True)
    base, fleet, ros = without["fleet_side"], with_bridge["fleet_side"], with_bridge["ros2_side"]
    print(f"fleet: {args.robots} robots x machine1 (6 sensors) x {args.rate:g} Hz, no local cache, "
          f"{args.duration:g} s per run")  # fmt: skip
    print(f"{'':34} {'samples/s':>10} {'p50 ms':>8} {'p99 ms':>8}")
    for label, row in (
        ("arpz client, no bridge", base),
        ("arpz client, bridge in the CEDDP", fleet),
        ("ROS 2 subscriber (through bridge)", ros),
    ):
        print(
            f"{label:34} {row['per_s']:>10.1f} {row['latency_ms_p50']!s:>8} "
            f"{row['latency_ms_p99']!s:>8}"
        )
    if ros["latency_ms_p50"] is not None and fleet["latency_ms_p50"] is not None:
        added = ros["latency_ms_p50"] - fleet["latency_ms_p50"]
        share = ros["per_s"] / fleet["per_s"] if fleet["per_s"] else 0.0
        print(f"through the bridge: {share:.3f}x the samples/s of the arpz client, "
              f"+{added:.3f} ms at p50")  # fmt: skip
    print(f"CEDDP ingest p50 without / with the bridge: {without['ceddp_latency_ms_p50']} / "
          f"{with_bridge['ceddp_latency_ms_p50']} ms")  # fmt: skip
    print(f"bridge counters: {with_bridge['bridge_counters']}")
    if args.json:
        Path(args.json).write_text(json.dumps([without, with_bridge], indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
