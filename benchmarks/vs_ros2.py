"""ROS 2 side by side: arpz's reliable channel against rclpy + Fast DDS and raw Zenoh, one run,
one table.

For each payload (24 B, 1 KiB, 64 KiB and a 921 600-byte 640 x 480 rgb8 frame) and each QoS
(RELIABLE VOLATILE KEEP_ALL, and KEEP_LAST depth 10), the three middlewares run one after the
other, each as a publisher process and a subscriber process (``benchmarks/vs_ros2_node.py``: the
perf tool's own loops, clocks and report for all three, rclpy's endpoints written as a ROS 2
engineer writes them: a node, its executor spinning in its own thread, UInt8MultiArray or
sensor_msgs/Image):

- **throughput**: the publisher flat out for a few seconds; msg/s and MB/s as received, what a
  KEEP_LAST history dropped on the way;
- **CPU per message** at each end: the publisher's and the subscriber's process CPU time (every
  thread) over the messages sent and received, and the whole path's (publisher + subscriber +
  Zenoh's router, which DDS has not) over the messages received;
- **round trip** p50 / p99 at 100 Hz and 1 kHz (``ping`` -> ``pong`` -> ``ping``);
- **loss** at 0 % and 10 % loss each way in the kernel lab (``arpz.lab``: the publisher in a
  robot's network namespace, the subscriber and the router in the server's, nftables dropping
  ``numgen random`` frames at the receiving end of each direction; a fresh lab a cell), a paced
  stream (``STREAM_RATE_HZ``), the loss applied once the publisher has matched: what has not
  arrived 10 s (``--quick``: 0.5 s) after the last send is lost; and the one-way p50 / p99 over
  every message sent, one never received counting as infinitely late ("never").

Zenoh (arpz and raw) goes through a router process as the project's other benchmarks do: TCP on
loopback, ``--lab-link`` (UDP: nothing but the channel recovers a lost datagram) from the robot's
namespace in the lab. rclpy goes peer to peer over Fast DDS, with its defaults except what the
measurement needs: a random ``ROS_DOMAIN_ID``, ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` (no shared
memory, as every Zenoh session here runs with ``shared_memory`` off: bytes cross the link, as
between a robot and its server), ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` on loopback and
``ROS_STATIC_PEERS`` (the other namespace's address) in the lab, whose subnets are routed: no
multicast between them. ``RMW_IMPLEMENTATION`` is respected.

Every row prints arpz / rclpy and arpz / raw Zenoh, and whether arpz is ahead of rclpy. Progress
goes to stderr a cell at a time, the table to stdout. Needs ROS 2's wheels (``pip install
'arpz[ros2]'``); the lab needs root (``--skip-lab``: loopback only, the loss at 0 % measured there).

    python benchmarks/vs_ros2.py --json /tmp/vs_ros2.json           # 16 min here
    python benchmarks/vs_ros2.py --quick --skip-lab --sizes 24       # the test's smoke run
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from importlib import metadata
from importlib.util import find_spec
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from arpz.lab import (  # noqa: E402
    Lab,
    LabInterrupted,
    LabUnavailable,
    LinkState,
    check_available,
    interrupt_on_signals,
)
from arpz.lab.fleet import process_cpu_s  # noqa: E402
from arpz.lab.names import CEDDP_ADDRESS  # noqa: E402
from arpz.tools.launch import LaunchError, Proc, free_port  # noqa: E402
from benchmarks.links import machine  # noqa: E402

NODE = str(ROOT / "benchmarks" / "vs_ros2_node.py")
MIDDLEWARES = ("arpz", "rclpy", "zenoh")
LABEL = {"arpz": "arpz", "rclpy": "rclpy + Fast DDS", "zenoh": "raw Zenoh"}
SIZES = (24, 1024, 65536, 921_600)
#: (name, perf flags); KEEP_LAST's depth as the issue sets it
QOS = {
    "keep_all": ("RELIABLE KEEP_ALL", ("--history", "keep_all")),
    "keep_last": ("RELIABLE KEEP_LAST(10)", ("--history", "keep_last", "--depth", "10")),
}
RTT_RATES_HZ = (100.0, 1000.0)
#: the paced stream of the loss cells, by payload: about what a robot sends of each
STREAM_RATE_HZ = {24: 1000.0, 1024: 1000.0, 65536: 100.0, 921_600: 10.0}
#: the loss each way of the lab's cells, %
LAB_LOSSES_PCT = (0.0, 10.0)
#: every Zenoh session of the run (router included), unless --shm
NO_SHM = "{ transport: { shared_memory: { enabled: false } } }\n"
#: the lab's router, in the server's namespace
LAB_UDP_PORT, LAB_TCP_PORT = 7447, 7448
#: seconds a publisher may take to start and match
START_S = 20.0
#: one measurement's figures by name (None: not measured; inf: never delivered)
Figures = dict[str, float | None]
SAY: Callable[[str], None] = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731


@dataclass(frozen=True)
class Plan:
    """How much each cell measures."""

    throughput_s: float
    rtt_count: dict[float, int]
    #: bytes a round trip cell sends at most one way (a 921 600-byte ping at 1 kHz is
    #: 0.9 GB/s, far past what one host moves: the count shrinks, the rate stays)
    rtt_bytes: int
    stream_s: float
    linger_s: float
    warmup_s: float

    def rtt_pings(self, rate_hz: float, size: int) -> int:
        return max(10, min(self.rtt_count[rate_hz], self.rtt_bytes // size))

    def stream_count(self, size: int) -> int:
        return max(5, round(STREAM_RATE_HZ.get(size, 100.0) * self.stream_s))


FULL = Plan(3.0, {100.0: 500, 1000.0: 3000}, 200_000_000, 5.0, 10.0, 1.0)
QUICK = Plan(0.2, {100.0: 20, 1000.0: 100}, 4_000_000, 0.3, 0.5, 0.2)


@dataclass(frozen=True)
class Cell:
    """One measurement of one middleware."""

    kind: str  # throughput | rtt | stream
    size: int
    qos: str
    middleware: str
    rate_hz: float = 0.0
    loss_pct: float = 0.0
    where: str = "loopback"  # loopback | lab

    @property
    def name(self) -> str:
        what = {
            "throughput": "throughput",
            "rtt": f"round trip {self.rate_hz:g} Hz",
            "stream": f"{self.rate_hz:g} Hz at {self.loss_pct:g} % loss ({self.where})",
        }[self.kind]
        return f"{self.size} B {self.qos} {what} {self.middleware}"


# ------------------------------------------------------------------------------ where it runs


@dataclass
class Site:
    """Loopback, or the kernel lab: where the processes of a cell run and how they connect."""

    workdir: Path
    shm: bool
    domain: int
    lab: Lab | None = None
    lab_link: str = "udp"
    router: Proc | None = None
    endpoint: str = ""
    procs: list[Proc] = field(default_factory=list)

    def zenoh_config(self) -> list[str]:
        if self.shm:
            return []
        path = self.workdir / "noshm.json5"
        path.write_text(NO_SHM, encoding="utf-8")
        return ["--zenoh-config", str(path)]

    def spawn(self, name: str, side: str, args: list[str], env: dict[str, str]) -> Proc:
        """``python ARGS`` on the robot's side (publisher, ping) or the server's."""
        if self.lab is None:
            proc = Proc.spawn(name, args, self.workdir, env=env)
        else:
            ns = self.lab.robot("robot1").namespace if side == "robot" else self.lab.ceddp_namespace
            proc = self.lab.spawn(name, ns, args, self.workdir, env=env)
        self.procs.append(proc)
        return proc

    def start_router(self) -> None:
        if self.lab is None:
            self.endpoint = f"tcp/127.0.0.1:{free_port()}"
            listen = self.endpoint
        else:
            listen = f"udp/{CEDDP_ADDRESS}:{LAB_UDP_PORT},tcp/{CEDDP_ADDRESS}:{LAB_TCP_PORT}"
        args = ["-m", "arpz.perf", "router", "--listen", listen, *self.zenoh_config()]
        self.router = self.spawn("router", "server", args, {})
        self.router.wait_line("listening", 30)

    def connect(self, side: str) -> str:
        """The Zenoh endpoint a process on ``side`` connects to."""
        if self.lab is None:
            return self.endpoint
        if side == "robot" and self.lab_link == "udp":
            return f"udp/{CEDDP_ADDRESS}:{LAB_UDP_PORT}"
        return f"tcp/{CEDDP_ADDRESS}:{LAB_TCP_PORT}"

    def ros_env(self, side: str) -> dict[str, str]:
        env = {
            "ROS_DOMAIN_ID": str(self.domain),
            "ROS_LOG_DIR": str(self.workdir / "ros_log"),
            "RCUTILS_COLORIZED_OUTPUT": "0",
        }
        if not self.shm:
            env["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"
        if self.lab is None:
            env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        else:
            robot = self.lab.robot("robot1").address
            env["ROS_STATIC_PEERS"] = CEDDP_ADDRESS if side == "robot" else robot
        return env

    def impair(self, loss_pct: float) -> None:
        if self.lab is not None:
            self.lab.apply("robot1", LinkState(loss_up_pct=loss_pct, loss_down_pct=loss_pct))

    def router_cpu_s(self) -> float:
        if self.router is None:
            return 0.0
        return process_cpu_s(self.router.popen.pid)

    def end(self, procs: list[Proc]) -> None:
        for proc in procs:
            proc.kill()
            self.procs.remove(proc)

    def close(self) -> None:
        for proc in reversed(self.procs):
            proc.kill()
        self.procs.clear()


@contextmanager
def loopback(workdir: Path, shm: bool, domain: int) -> Iterator[Site]:
    site = Site(workdir / "loopback", shm, domain)
    site.workdir.mkdir(parents=True, exist_ok=True)
    try:
        site.start_router()
        yield site
    finally:
        site.close()


@contextmanager
def lab_site(workdir: Path, args: argparse.Namespace, domain: int, router: bool) -> Iterator[Site]:
    """A fresh lab with one robot, and Zenoh's router in the server's namespace if ``router``."""
    site = Site(workdir / "lab", args.shm, domain, lab_link=args.lab_link)
    site.workdir.mkdir(parents=True, exist_ok=True)
    with Lab.create(["robot1"]) as lab:
        site.lab = lab
        try:
            if router:
                site.start_router()
            yield site
        finally:
            site.close()


# ------------------------------------------------------------------------------ one cell


class CellFailed(RuntimeError):
    pass


def node_args(cell: Cell, role: str, site: Site, side: str, key: str) -> list[str]:
    """``vs_ros2_node.py`` for one process of ``cell``."""
    if cell.middleware == "rclpy":
        head = [NODE, "rclpy", role, "--connect", "-", "--transport", "zenoh"]
    else:
        transport = "arpz" if cell.middleware == "arpz" else "zenoh"
        head = [NODE, "zenoh", role, "--connect", site.connect(side), "--transport", transport]
        head += site.zenoh_config()
    return [*head, "--key", key, "--size", str(cell.size), *QOS[cell.qos][1]]


def env_for(cell: Cell, site: Site, side: str) -> dict[str, str]:
    return site.ros_env(side) if cell.middleware == "rclpy" else {}


def last_json(proc: Proc, timeout_s: float) -> dict[str, Any]:
    try:
        code = proc.popen.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise CellFailed(
            f"{proc.name} did not end within {timeout_s:.0f} s: {proc.tail(5)}"
        ) from None
    proc.kill()  # reaps it and joins its output's reader
    lines = [line for line in proc.lines if line.startswith("{")]
    if code != 0 or not lines:
        raise CellFailed(f"{proc.name} exited {code}: {proc.tail(8)}")
    result: dict[str, Any] = json.loads(lines[-1])
    return result


def run_cell(cell: Cell, site: Site, plan: Plan, tag: str) -> dict[str, Any]:
    """Start the cell's two processes; their reports, and the router's CPU meanwhile. Both
    start at once: a publisher (or ping) waits until it has matched."""
    procs: list[Proc] = []
    cpu0 = site.router_cpu_s()

    def start(role: str, side: str, extra: list[str]) -> Proc:
        args = [*node_args(cell, role, site, side, f"vs_ros2/{tag}"), *extra]
        proc = site.spawn(f"{tag}-{role}", side, args, env_for(cell, site, side))
        procs.append(proc)
        return proc

    latencies = site.workdir / f"{tag}-latency.npy"
    try:
        if cell.kind == "rtt":
            report = round_trips(cell, plan, start, latencies)
            return {"ping": report, "router_cpu_s": site.router_cpu_s() - cpu0}
        pub, sub = stream(cell, site, plan, start, latencies)
        return {"pub": pub, "sub": sub, "router_cpu_s": site.router_cpu_s() - cpu0}
    finally:
        site.end(procs)
        if cell.loss_pct:
            site.impair(0.0)


Start = Callable[[str, str, list[str]], Proc]


def round_trips(cell: Cell, plan: Plan, start: Start, latencies: Path) -> dict[str, Any]:
    """``pong`` on the server's side, ``ping`` on the robot's; the ping's report."""
    count = plan.rtt_pings(cell.rate_hz, cell.size)
    express = [] if cell.middleware == "rclpy" else ["--express"]  # Zenoh's latency setting
    start("pong", "server", express)
    ping = start(
        "ping",
        "robot",
        [
            *express,
            *("--rate", f"{cell.rate_hz:g}", "--count", str(count)),
            *("--warmup", f"{plan.warmup_s:g}", "--idle-timeout", f"{plan.linger_s:g}"),
            *("--latency-out", str(latencies)),
        ],
    )
    report = last_json(ping, 120 + count / cell.rate_hz)
    report["delivery_us"] = delivery_percentiles(latencies, report["sent"], report["received"])
    return report


def stream(
    cell: Cell, site: Site, plan: Plan, start: Start, latencies: Path
) -> tuple[dict[str, Any], dict[str, Any]]:
    """A publisher flat out (throughput) or paced (stream) on the robot's side, a subscriber
    on the server's; a stream's loss starts once the publisher has matched."""
    if cell.kind == "throughput":
        pace = ["--rate", "0", "--duration", f"{plan.throughput_s:g}"]
        length, counted = plan.throughput_s, []
    else:
        count = plan.stream_count(cell.size)
        pace = ["--rate", f"{cell.rate_hz:g}", "--count", str(count)]
        length = count / cell.rate_hz
        # the subscriber knows the count too: the publisher's end marker can be lost with
        # what it sent (a DDS writer gone before its repairs)
        counted = ["--count", str(count), "--latency-out", str(latencies)]
    # without the end marker, the subscriber stops once the publisher's linger is long over
    bound = START_S + plan.warmup_s + length + 2 * plan.linger_s
    sub = start(
        "sub",
        "server",
        [*pace[:2], "--idle-timeout", f"{plan.linger_s:g}", "--duration", f"{bound:g}", *counted],
    )
    pub = start(
        "pub", "robot", [*pace, "--warmup", f"{plan.warmup_s:g}", "--linger", f"{plan.linger_s:g}"]
    )
    if cell.loss_pct:
        pub.wait_line("matched", 60)
        site.impair(cell.loss_pct)
    pub_report = last_json(pub, 60 + bound)
    sub_report = last_json(sub, 60 + bound)
    if cell.kind == "stream":
        sub_report["delivery_us"] = delivery_percentiles(
            latencies, pub_report["sent"], sub_report["received"]
        )
    return pub_report, sub_report


# ------------------------------------------------------------------------------ figures


def figures(cell: Cell, raw: dict[str, Any]) -> Figures:
    """The figures of one measurement the table reads."""
    if cell.kind == "rtt":
        ping = raw["ping"]
        p50, p99 = ping["delivery_us"]
        return {
            "p50_us": p50,
            "p99_us": p99,
            "lost_pct": lost_pct(ping["sent"], ping["received"]),
        }
    pub, sub = raw["pub"], raw["sub"]
    out: Figures = {"lost_pct": lost_pct(pub["sent"], sub["received"])}
    if cell.kind == "stream":
        p50, p99 = sub["delivery_us"]
        out |= {"p50_ms": p50 / 1000, "p99_ms": p99 / 1000}
    if cell.kind == "throughput":
        received = sub["received"]
        cpu_s = pub["cpu_s"] + sub["cpu_s"] + raw["router_cpu_s"]
        out |= {
            "msg_s": sub["throughput_msg_s"],
            "mb_s": sub["throughput_msg_s"] * cell.size / 1e6,
            "cpu_pub_us": pub["cpu_us_per_msg"],
            "cpu_sub_us": sub["cpu_us_per_msg"],
            "cpu_all_us": 1e6 * cpu_s / received if received else None,
            "cpu_router_us": 1e6 * raw["router_cpu_s"] / received if received else None,
        }
    return out


def delivery_percentiles(path: Path, sent: int, received: int) -> tuple[float, float]:
    """p50 and p99 (us) of the delivery times of every sample sent, one never delivered
    counting as infinitely late: the survivors' percentiles flatter a middleware that loses
    the slow ones. ``inf`` when more than 50 % (1 %) never came."""
    import numpy as np

    got = np.load(path) if path.exists() else np.zeros(0)
    path.unlink(missing_ok=True)
    if sent <= 0:
        return math.inf, math.inf
    values = np.sort(got)[: min(sent, received)]  # a duplicate is not a second delivery
    padded = np.concatenate([values, np.full(sent - len(values), math.inf)])
    p50, p99 = (padded[max(0, math.ceil(q * sent) - 1)] for q in (0.5, 0.99))
    return float(p50), float(p99)


def lost_pct(sent: int, received: int) -> float:
    return 100.0 * max(0, sent - received) / sent if sent else 100.0


def median_of(values: list[Figures], key: str) -> float | None:
    found = [v[key] for v in values if v.get(key) is not None]
    return statistics.median(found) if found else None  # type: ignore[type-var]


# ------------------------------------------------------------------------------ the table


@dataclass(frozen=True)
class Metric:
    """A row of the table: where its figures come from, how to print them, which way is
    better."""

    label: str
    kind: str
    keys: tuple[str, ...]
    fmt: Callable[[Figures], str]
    lower_is_better: bool = True
    rate_hz: float = 0.0
    loss_pct: float | None = None


def _num(value: float | None, digits: int = 0) -> str:
    if value is None:
        return "-"
    return f"{value:,.{digits}f}".replace(",", " ")


def _sig(value: float | None) -> str:
    """Three significant figures or so."""
    if value is None:
        return "-"
    if math.isinf(value):
        return "never"
    if abs(value) >= 100:
        return _num(value)
    return f"{value:.1f}" if abs(value) >= 10 else f"{value:.2f}"


def _throughput(f: Figures) -> str:
    text = f"{_num(f.get('msg_s'))} ({_sig(f.get('mb_s'))} MB/s)"
    lost = f.get("lost_pct")
    return text + (f", {lost:.1f} % dropped" if lost else "")


def _pair(unit_key: str, div: float = 1.0) -> Callable[[Figures], str]:
    def fmt(f: Figures) -> str:
        a, b = f.get(f"p50_{unit_key}"), f.get(f"p99_{unit_key}")
        text = f"{_sig(None if a is None else a / div)} / {_sig(None if b is None else b / div)}"
        lost = f.get("lost_pct")
        return text + (f" ({lost:.1f} % lost)" if lost else "")

    return fmt


def _cpu(key: str) -> Callable[[Figures], str]:
    return lambda f: _sig(f.get(key))


def _lost(f: Figures) -> str:
    lost = f.get("lost_pct")
    return "-" if lost is None else f"{lost:.1f} %"


def metrics(lab_losses: tuple[float, ...]) -> list[Metric]:
    """The rows of a payload and QoS, in order (``lab_losses`` empty: no lab, the loss cells
    on loopback at 0 %)."""
    rows = [
        Metric("throughput, msg/s (MB/s)", "throughput", ("msg_s",), _throughput, False),
        *(
            Metric(f"CPU us/msg, {who}", "throughput", (key,), _cpu(key))
            for who, key in (
                ("publisher", "cpu_pub_us"),
                ("subscriber", "cpu_sub_us"),
                ("all processes", "cpu_all_us"),
            )
        ),
        *(
            Metric(
                f"round trip {r:g} Hz, p50 / p99 ms",
                "rtt",
                ("p50_us", "p99_us"),
                _pair("us", 1000),
                rate_hz=r,
            )
            for r in RTT_RATES_HZ
        ),
    ]
    where = "lab" if lab_losses else "loopback"
    for pct in lab_losses or (0.0,):
        rows += [
            Metric(f"lost, {pct:g} % loss ({where})", "stream", ("lost_pct",), _lost, loss_pct=pct),
            Metric(
                f"one-way p50 / p99 ms, {pct:g} % loss",
                "stream",
                ("p50_ms", "p99_ms"),
                _pair("ms"),
                loss_pct=pct,
            ),
        ]
    return rows


def ratio(ours: float | None, theirs: float | None) -> str:
    if ours is None or theirs is None:
        return "-"
    if math.isinf(ours) or math.isinf(theirs):
        return "=" if ours == theirs else ("inf" if math.isinf(ours) else "0.00x")
    if theirs == 0:
        return "=" if ours == 0 else "inf"
    return f"{ours / theirs:.2f}x"


def ahead(metric: Metric, ours: Figures, theirs: Figures) -> str:
    """Whether arpz is ahead of the baseline on every figure of the row."""
    verdicts = set()
    for key in metric.keys:
        a, b = ours.get(key), theirs.get(key)
        if a is None or b is None:  # not measured
            continue
        if a == b:
            verdicts.add("tie")
        else:
            verdicts.add("yes" if (a < b) == metric.lower_is_better else "no")
    if not verdicts:
        return "-"
    if len(verdicts) == 1:
        return verdicts.pop()
    return "yes" if verdicts == {"yes", "tie"} else "mixed"


def table(
    results: dict[tuple[str, int, str, float, float], dict[str, Figures]],
    sizes: list[int],
    qoses: list[str],
    lab_losses: tuple[float, ...],
    middlewares: tuple[str, ...],
) -> tuple[list[str], list[dict[str, Any]]]:
    """The printed lines and the rows (for --json)."""
    head = ["payload", "QoS", "metric", *(LABEL[m] for m in middlewares)]
    if "arpz" in middlewares:
        head += [f"arpz / {LABEL[m]}" for m in middlewares if m != "arpz"]
        if "rclpy" in middlewares:
            head.append("arpz ahead of rclpy")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    rows = []
    for size in sizes:
        for qos in qoses:
            for metric in metrics(lab_losses):
                where = (metric.kind, size, qos, metric.rate_hz, metric.loss_pct or 0.0)
                per = results.get(where, {})
                if not per:
                    continue
                cells = [metric.fmt(per[m]) if m in per else "-" for m in middlewares]
                row: dict[str, Any] = {
                    "size": size,
                    "qos": qos,
                    "metric": metric.label,
                    "figures": {m: per.get(m) for m in middlewares},
                }
                if "arpz" in per:
                    for base in (m for m in middlewares if m != "arpz"):
                        theirs = per.get(base, {})
                        text = " / ".join(
                            ratio(per["arpz"].get(k), theirs.get(k)) for k in metric.keys
                        )
                        cells.append(text)
                        row[f"arpz/{base}"] = text
                    if "rclpy" in middlewares:
                        verdict = ahead(metric, per["arpz"], per.get("rclpy", {}))
                        cells.append(verdict)
                        row["arpz_ahead_of_rclpy"] = verdict
                rows.append(row)
                lines.append(
                    "| " + " | ".join([f"{size} B", QOS[qos][0], metric.label, *cells]) + " |"
                )
    return lines, rows


# ------------------------------------------------------------------------------ the run


def plan_cells(
    sizes: list[int],
    qoses: list[str],
    middlewares: tuple[str, ...],
    lab_losses: tuple[float, ...],
    where: str,
) -> list[Cell]:
    cells = []
    for size in sizes:
        for qos in qoses:
            if where == "loopback":
                kinds = [("throughput", 0.0, 0.0), *(("rtt", r, 0.0) for r in RTT_RATES_HZ)]
                if not lab_losses:
                    kinds.append(("stream", STREAM_RATE_HZ.get(size, 100.0), 0.0))
            else:
                rate = STREAM_RATE_HZ.get(size, 100.0)
                kinds = [("stream", rate, pct) for pct in lab_losses]
            for kind, rate_hz, loss in kinds:
                cells += [Cell(kind, size, qos, mw, rate_hz, loss, where) for mw in middlewares]
    return cells


def describe(cell: Cell, f: Figures) -> str:
    if cell.kind == "throughput":
        return (
            f"{_throughput(f)}, CPU us/msg pub {_sig(f.get('cpu_pub_us'))} sub "
            f"{_sig(f.get('cpu_sub_us'))} all {_sig(f.get('cpu_all_us'))}"
        )
    if cell.kind == "rtt":
        return f"round trip p50 / p99 {_pair('us', 1000)(f)} ms"
    return f"lost {_sig(f.get('lost_pct'))} %, one-way p50 / p99 {_pair('ms')(f)} ms"


@dataclass
class Run:
    """What a run measured: each cell's figures a round, the processes' reports, failures."""

    measured: dict[Cell, list[Figures]] = field(default_factory=dict)
    raw: list[dict[str, Any]] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    cells: int = 0

    def results(self) -> dict[tuple[str, int, str, float, float], dict[str, Figures]]:
        """The median of the rounds, by (kind, size, QoS, rate, loss) and middleware."""
        out: dict[tuple[str, int, str, float, float], dict[str, Figures]] = {}
        for cell, values in self.measured.items():
            merged = {k: median_of(values, k) for k in {k for v in values for k in v}}
            rate = cell.rate_hz if cell.kind == "rtt" else 0.0
            out.setdefault((cell.kind, cell.size, cell.qos, rate, cell.loss_pct), {})[
                cell.middleware
            ] = merged
        return out


def measure(args: argparse.Namespace, middlewares: tuple[str, ...], wheres: list[str]) -> Run:
    """Every cell, a site at a time (loopback, then the lab), rounds interleaved in each."""
    plan = QUICK if args.quick else FULL
    domain = random.randint(1, 100)  # rclpy's: no other ROS 2 node of the host joins
    work = args.workdir or Path(tempfile.mkdtemp(prefix="arpz-vs-ros2-"))
    plans = {w: plan_cells(args.sizes, args.qos, middlewares, args.lab_losses, w) for w in wheres}
    run = Run(cells=sum(len(cells) for cells in plans.values()) * args.rounds)
    started = time.monotonic()
    for where in wheres:
        rounds = [(r, cell) for r in range(args.rounds) for cell in plans[where]]
        with loopback(work, args.shm, domain) if where == "loopback" else nullcontext() as shared:
            for round_no, cell in rounds:
                done = len(run.raw) + len(run.failures) + 1
                prefix = f"[{done}/{run.cells} {time.monotonic() - started:.0f} s]"
                t0 = time.monotonic()
                tag = f"r{round_no}_{done}_{cell.middleware}"
                try:
                    # a lab of its own for every lab cell: what a cell leaves in the kernel
                    # (sockets, neighbours, datagrams half reassembled) never meets the next
                    with (
                        nullcontext(shared)
                        if shared is not None
                        else lab_site(work, args, domain, router=cell.middleware != "rclpy")
                    ) as site:
                        result = run_cell(cell, site, plan, tag)
                except (CellFailed, LaunchError, OSError) as exc:
                    run.failures.append(f"{cell.name}: {exc}")
                    SAY(f"{prefix} {cell.name}: FAILED {str(exc).splitlines()[0]}")
                    continue
                figs = figures(cell, result)
                run.measured.setdefault(cell, []).append(figs)
                run.raw.append({"cell": cell.__dict__, "round": round_no, **result})
                took = time.monotonic() - t0
                SAY(f"{prefix} {cell.name}: {describe(cell, figs)} ({took:.1f} s)")
    return run


def parse(argv: list[str] | None) -> tuple[argparse.Namespace, tuple[str, ...], list[str]]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--quick", action="store_true", help="small counts (a smoke test)")
    ap.add_argument("--json", type=Path, help="write the figures and the table here")
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="payload bytes")
    ap.add_argument("--qos", nargs="+", choices=list(QOS), default=list(QOS))
    where = ap.add_mutually_exclusive_group()
    where.add_argument("--skip-lab", action="store_true", help="loopback only (no root needed)")
    where.add_argument("--lab-only", action="store_true", help="only the loss cells of the lab")
    ap.add_argument(
        "--middlewares", default=",".join(MIDDLEWARES), help="comma-separated subset of %(default)s"
    )
    ap.add_argument("--rounds", type=int, default=1, help="interleaved; medians reported")
    ap.add_argument(
        "--losses",
        type=float,
        nargs="+",
        default=list(LAB_LOSSES_PCT),
        help="%% loss each way of the lab's cells",
    )
    ap.add_argument("--lab-link", choices=("udp", "tcp"), default="udp", help="arpz's and Zenoh's")
    ap.add_argument(
        "--shm", action="store_true", help="leave shared memory to each middleware's default"
    )
    ap.add_argument("--workdir", type=Path, help="logs of every process (default: temporary)")
    args = ap.parse_args(argv)
    chosen = args.middlewares.split(",")
    middlewares = tuple(m for m in MIDDLEWARES if m in chosen)
    if not middlewares or set(chosen) - set(MIDDLEWARES):
        ap.error(f"--middlewares: a subset of {','.join(MIDDLEWARES)}")
    if min(args.sizes) < 16:
        ap.error("--sizes: at least 16 bytes (sequence number and send stamp)")
    if args.rounds < 1:
        ap.error("--rounds: at least 1")
    if not all(0 <= pct <= 100 for pct in args.losses):
        ap.error("--losses: percentages from 0 to 100")
    wheres = ["loopback"] if args.skip_lab else ["lab"] if args.lab_only else ["loopback", "lab"]
    args.lab_losses = () if args.skip_lab else tuple(args.losses)
    return args, middlewares, wheres


def main(argv: list[str] | None = None) -> int:
    args, middlewares, wheres = parse(argv)
    if "rclpy" in middlewares and find_spec("rclpy") is None:
        SAY(
            "vs_ros2: ROS 2 is not installed (pip install 'arpz[ros2]', or source a ROS 2 "
            "with rclpy); --middlewares arpz,zenoh runs without it"
        )
        return 2
    if "lab" in wheres:
        try:
            check_available()
        except LabUnavailable as exc:
            SAY(f"vs_ros2: {exc}; --skip-lab measures loopback only")
            return 2
    about = machine() | {
        "load_at_start": os.getloadavg(),
        "rmw": os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp"),
        "fastdds": _version("ros-fastdds"),
        "rclpy": _version("ros-rclpy"),
    }
    started = time.monotonic()
    try:
        with interrupt_on_signals():
            run = measure(args, middlewares, wheres)
    except LabInterrupted as exc:
        SAY(f"vs_ros2: {exc}")
        return 130
    about["load_at_end"] = os.getloadavg()
    lines, rows = table(run.results(), args.sizes, args.qos, args.lab_losses, middlewares)
    shm = "on (each middleware's default)" if args.shm else "off"
    plan = QUICK if args.quick else FULL
    print(
        f"\narpz vs rclpy + Fast DDS vs raw Zenoh: {run.cells} cells in "
        f"{time.monotonic() - started:.0f} s, {args.rounds} round(s)"
        f"{', quick' if args.quick else ''}; shared memory {shm}; lab link "
        f"{args.lab_link if 'lab' in wheres else '-'}"
    )
    print(
        f"machine: {about['cpu']}, {about['cores']} cores, kernel {about['kernel']}, Python "
        f"{about['python']}, zenoh {about['zenoh']}, rclpy {about['rclpy']} on "
        f"{about['rmw']} (Fast DDS {about['fastdds']}), commit {about['commit']}, "
        f"{about['date']}; load average {about['load_at_start'][0]:.1f} at the start, "
        f"{about['load_at_end'][0]:.1f} at the end\n"
    )
    print("\n".join(lines))
    streams = ", ".join(f"{s} B at {r:g} Hz" for s, r in STREAM_RATE_HZ.items())
    print(
        "\nCPU: process time of every thread over the messages sent (publisher) or received "
        "(subscriber; all processes: publisher + subscriber + Zenoh's router, over received). "
        f"Loss: a paced stream ({streams}), lost = not received {plan.linger_s:g} s after the "
        "last send; p50 / p99 over every message sent, one never received counting as "
        "infinitely late (never)."
    )
    for failure in run.failures:
        print(f"FAILED {failure}")
    if args.json:
        doc = {"machine": about, "quick": args.quick, "rows": rows, "runs": run.raw}
        doc["failures"] = run.failures
        args.json.write_text(json.dumps(finite(doc), indent=2) + "\n", encoding="utf-8")
    return 1 if run.failures else 0


def finite(value: Any) -> Any:
    """``value`` for JSON: a delivery time of ``inf`` (never delivered) becomes null."""
    if isinstance(value, float) and math.isinf(value):
        return None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "not installed"


if __name__ == "__main__":
    sys.exit(main())
