"""Build a model file from a running fleet, and compare expected with measured performance.

The paper characterised its nodes by hand with htop and rqt; an arpz fleet reports the same
figures itself: each robot agent publishes ``RobotStats`` (its CPU and per-topic rates and
bytes), the CEDDP publishes ``CeddpStats`` (its CPU and what arrives per robot topic) and every
robot ``Announce``s the rate it is configured for. From a few seconds of these:

* a model file: a computer per robot and one server; a node per arpz process (each robot agent,
  pinned to its robot, and the CEDDP, pinned to the server) at its measured CPU; a message per
  robot topic at its measured bandwidth; a link per robot to the server;
* eq. 10 of the paper for the running configuration, per robot topic:
  P_measured = P_expected * F_measured / F_expected, with F_expected the announced rate and
  F_measured the rate the CEDDP received (what the fleet's performance actually depends on).

Pure logic (``build_model``, ``eq10``) takes observations and returns values; ``listen`` is the
only function that touches a transport, and ``main`` the only one that opens Zenoh.
"""

from __future__ import annotations

import argparse
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgspec

from arpz.configure.eq10 import Eq10Node, summarise, summary_text
from arpz.configure.model import (
    Computer,
    Link,
    Message,
    Model,
    Node,
    Setting,
    dump_json,
    dump_toml,
    fixed_setting,
    load_model,
)
from arpz.core import keys
from arpz.core.messages import (
    ANNOUNCE_DECODER,
    CEDDP_STATS_DECODER,
    STATS_DECODER,
    Announce,
    CeddpStats,
    RobotStats,
)
from arpz.core.transport import Transport
from arpz.runtime.startup import fail

SERVER = "server"
CEDDP_NODE = "ceddp"


@dataclass
class Observations:
    """What was heard from the fleet, by robot."""

    robot_stats: dict[str, list[RobotStats]] = field(default_factory=dict)
    ceddp: list[CeddpStats] = field(default_factory=list)
    announce: dict[str, Announce] = field(default_factory=dict)
    undecodable: int = 0


def listen(transport: Transport, fleet: str, duration_s: float) -> Observations:
    """Subscribe to stats and announcements for ``duration_s``. Callbacks only decode and
    append under a lock (they run on Zenoh's thread and must not block)."""
    obs = Observations()
    lock = threading.Lock()

    def on_stats(key: str, payload: bytes, _att: bytes | None) -> None:
        try:
            stats = STATS_DECODER.decode(payload)
        except msgspec.DecodeError:
            with lock:
                obs.undecodable += 1
            return
        with lock:
            obs.robot_stats.setdefault(stats.robot, []).append(stats)

    def on_ceddp(key: str, payload: bytes, _att: bytes | None) -> None:
        try:
            stats = CEDDP_STATS_DECODER.decode(payload)
        except msgspec.DecodeError:
            with lock:
                obs.undecodable += 1
            return
        with lock:
            obs.ceddp.append(stats)

    def on_announce(key: str, payload: bytes, _att: bytes | None) -> None:
        try:
            ann = ANNOUNCE_DECODER.decode(payload)
        except msgspec.DecodeError:
            with lock:
                obs.undecodable += 1
            return
        with lock:
            obs.announce[ann.robot] = ann

    handles = [
        transport.subscribe(keys.all_stats(fleet), on_stats),
        transport.subscribe(keys.ceddp_stats_key(fleet), on_ceddp),
        transport.subscribe(keys.all_announce(fleet), on_announce),
    ]
    try:
        time.sleep(duration_s)
    finally:
        for handle in handles:
            handle.undeclare()
    with lock:
        return Observations(
            robot_stats={k: list(v) for k, v in obs.robot_stats.items()},
            ceddp=list(obs.ceddp),
            announce=dict(obs.announce),
            undecodable=obs.undecodable,
        )


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else 0.0


def _robots(obs: Observations) -> list[str]:
    names = set(obs.robot_stats) | set(obs.announce)
    for report in obs.ceddp:
        names.update(t.robot for t in report.topics)
    return sorted(names)


def measured_rates(obs: Observations) -> dict[tuple[str, str], tuple[float, float]]:
    """(robot, topic) -> (rate Hz, bytes/s): the CEDDP's arrivals averaged over its reports,
    else the robot's own counters (rate_hz, and bytes_sent over the time between reports)."""
    rates: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for report in obs.ceddp:
        for t in report.topics:
            rates.setdefault((t.robot, t.topic), []).append((t.rate_hz, t.bytes_per_s))
    out = {k: (_mean([r for r, _ in v]), _mean([b for _, b in v])) for k, v in rates.items()}
    for robot, reports in obs.robot_stats.items():
        reports = sorted(reports, key=lambda s: s.stamp_ns)
        for topic in {t for s in reports for t in s.topics}:
            if (robot, topic) in out:
                continue
            seen = [s for s in reports if topic in s.topics]
            rate = _mean([s.topics[topic].rate_hz for s in seen])
            bps = 0.0
            if len(seen) >= 2 and seen[-1].stamp_ns > seen[0].stamp_ns:
                sent = seen[-1].topics[topic].bytes_sent - seen[0].topics[topic].bytes_sent
                bps = max(sent, 0) / ((seen[-1].stamp_ns - seen[0].stamp_ns) / 1e9)
            out[(robot, topic)] = (rate, bps)
    return out


def held_back_rates(obs: Observations) -> dict[tuple[str, str], float]:
    """(robot, topic) -> readings per second the robot's local cache held back (unchanged
    values the CEDDP already knows), from the first and last report of the window."""
    out: dict[tuple[str, str], float] = {}
    for robot, reports in obs.robot_stats.items():
        reports = sorted((s for s in reports if not s.final), key=lambda s: s.stamp_ns)
        if len(reports) < 2 or reports[-1].stamp_ns <= reports[0].stamp_ns:
            continue
        span_s = (reports[-1].stamp_ns - reports[0].stamp_ns) / 1e9
        for topic in reports[-1].topics:
            if topic in reports[0].topics:
                held = reports[-1].topics[topic].held_back - reports[0].topics[topic].held_back
                out[(robot, topic)] = max(held, 0) / span_s
    return out


def build_model(
    obs: Observations,
    *,
    robot_capacity: float = 100.0,
    server_capacity: float = 400.0,
    wireless_bandwidth: float = 54000.0,
    fleet: str = "",
) -> Model:
    """A model of the running fleet. CPU is in % of one core of the machine that measured it,
    as the paper normalises to a baseline computer; give capacities in the same unit."""
    robots = _robots(obs)
    rates = measured_rates(obs)
    computers = [Computer(name=r, kind="robot", capacity=robot_capacity) for r in robots]
    computers.append(Computer(name=SERVER, kind="server", capacity=server_capacity))
    share = wireless_bandwidth / max(len(robots), 1)
    links = [Link(between=(r, SERVER), bandwidth=share) for r in robots]
    nodes: list[Node] = []
    messages: list[Message] = []
    for robot in robots:
        cpu = _mean([s.cpu_percent for s in obs.robot_stats.get(robot, []) if not s.final])
        freq = sum(rate for (r, _), (rate, _) in rates.items() if r == robot)
        nodes.append(
            Node(
                name=f"{robot}_agent",
                residence=[robot],
                process=f"arpz robot agent {robot}",
                settings=[
                    Setting(cpu=round(cpu, 2), performance=100.0, frequency_hz=round(freq, 3))
                ],
            )
        )
        for (r, _topic), (_rate, bps) in sorted(rates.items()):
            if r == robot:
                messages.append(
                    Message(source=f"{robot}_agent", to=CEDDP_NODE, bandwidth=round(bps, 1))
                )

    ceddp_cpu = _mean([s.cpu_percent for s in obs.ceddp])
    ceddp_freq = sum(rate for rate, _ in rates.values())
    nodes.append(
        Node(
            name=CEDDP_NODE,
            residence=[SERVER],
            process="arpz CEDDP",
            settings=[
                Setting(
                    cpu=round(ceddp_cpu, 2), performance=100.0, frequency_hz=round(ceddp_freq, 3)
                )
            ],
        )
    )
    weight = 1.0 / len(nodes)
    nodes = [msgspec.structs.replace(n, weight=weight) for n in nodes]
    return Model(
        name=f"characterised fleet {fleet}".strip(),
        description="measured by python -m arpz.configure characterise (CPU in % of one core)",
        computers=computers,
        links=links,
        nodes=nodes,
        messages=messages,
    )


@dataclass(frozen=True)
class Eq10Row:
    robot: str
    topic: str
    f_expected_hz: float
    #: arrived at the CEDDP + held back by the robot's local cache (both are readings the CEDDP
    #: knows: a held-back reading is an unchanged value, not a lost one)
    f_measured_hz: float
    p_expected: float
    p_measured: float
    f_arrived_hz: float = 0.0
    f_held_back_hz: float = 0.0


def eq10(obs: Observations, expected: Model | None = None) -> list[Eq10Row]:
    """P_measured = P_expected * F_measured / F_expected for every announced robot topic.

    P_expected is the running setting's performance of the robot's agent node in ``expected``
    (a model file of the configuration being run: its fixed setting), else 100. F_measured
    counts readings held back by the local cache with those that arrived: the paper's nodes
    publish every reading, an arpz robot sends only the ones that changed.
    """
    rates = measured_rates(obs)
    held = held_back_rates(obs)
    perf: dict[str, float] = {}
    if expected is not None:
        for node in expected.nodes:
            perf[node.name] = fixed_setting(node).performance
    rows: list[Eq10Row] = []
    for robot, ann in sorted(obs.announce.items()):
        p_exp = perf.get(f"{robot}_agent", perf.get(robot, 100.0))
        for info in ann.sensors:
            f_exp = info.rate_hz
            arrived = rates.get((robot, info.topic), (0.0, 0.0))[0]
            kept = held.get((robot, info.topic), 0.0)
            f_meas = arrived + kept
            p_meas = p_exp * f_meas / f_exp if f_exp > 0 else 0.0
            rows.append(
                Eq10Row(robot, info.topic, f_exp, f_meas, p_exp, round(p_meas, 2), arrived, kept)
            )
    return rows


def eq10_text(rows: list[Eq10Row], weights: dict[str, float] | None = None) -> str:
    if not rows:
        return "eq. 10: no announced topics heard\n"
    lines = [
        "F meas = arrived at the CEDDP + held back (unchanged) by the robot's local cache",
        f"{'robot':<12} {'topic':<12} {'F exp Hz':>9} {'arrived':>8} {'held':>8} {'F meas':>8} "
        f"{'P exp':>7} {'P meas':>7} {'dev %':>6}",
    ]
    for r in rows:
        dev = 100.0 * (r.p_measured - r.p_expected) / r.p_expected if r.p_expected else 0.0
        lines.append(
            f"{r.robot:<12} {r.topic:<12} {r.f_expected_hz:>9.2f} {r.f_arrived_hz:>8.2f}"
            f" {r.f_held_back_hz:>8.2f} {r.f_measured_hz:>8.2f}"
            f" {r.p_expected:>7.2f} {r.p_measured:>7.2f} {dev:>6.1f}"
        )
    lines.append("per node (each robot agent: its topics' frequencies summed), eq. 10:")
    return "\n".join(lines) + "\n" + summary_text(summarise(eq10_nodes(rows, weights)))


def eq10_nodes(rows: list[Eq10Row], weights: dict[str, float] | None = None) -> list[Eq10Node]:
    """Eq. 10 per node, as the paper applies it: a robot agent's frequency is the sum of its
    topics', its weight the expected model's (equal weights without one)."""
    robots = sorted({r.robot for r in rows})
    nodes = []
    for robot in robots:
        mine = [r for r in rows if r.robot == robot]
        name = f"{robot}_agent"
        nodes.append(
            Eq10Node(
                name=name,
                weight=(weights or {}).get(name, 1.0 / len(robots)),
                p_expected=mine[0].p_expected,
                f_expected_hz=sum(r.f_expected_hz for r in mine),
                f_measured_hz=sum(r.f_measured_hz for r in mine),
            )
        )
    return nodes


def main(args: argparse.Namespace) -> int:
    from arpz.configure.model import ModelError
    from arpz.core.transport import SessionSettings, TransportError
    from arpz.transport.zenoh import ZenohTransport

    expected = None
    if args.expected:
        try:
            expected = load_model(args.expected)
        except ModelError as exc:
            return fail("configure characterise", str(exc))
    try:
        keys.fleet_prefix(args.fleet)
        transport = ZenohTransport.open(
            SessionSettings(mode="client", connect=[args.connect]), timeout_s=5.0
        )
    except (TransportError, ValueError) as exc:
        return fail("configure characterise", str(exc))
    try:
        print(
            f"listening to fleet {args.fleet!r} on {args.connect} for {args.duration:g} s",
            flush=True,
        )
        obs = listen(transport, args.fleet, args.duration)
    finally:
        transport.close()
    if not _robots(obs) and not obs.ceddp:
        return fail(
            "configure characterise",
            f"heard nothing from fleet {args.fleet!r} on {args.connect}",
            3,
        )
    model = build_model(
        obs,
        robot_capacity=args.robot_capacity,
        server_capacity=args.server_capacity,
        wireless_bandwidth=args.link_bandwidth,
        fleet=args.fleet,
    )
    out = Path(args.out)
    out.write_bytes(dump_toml(model).encode() if out.suffix == ".toml" else dump_json(model))
    print(
        f"wrote {out}: {len(model.computers)} computers, {len(model.nodes)} nodes, "
        f"{len(model.messages)} messages"
    )
    for node in model.nodes:
        s = node.settings[0]
        print(f"  {node.name:<20} cpu {s.cpu:>7.2f} %  messages {s.frequency_hz or 0:>8.2f} Hz")
    weights = {n.name: n.weight for n in expected.nodes} if expected is not None else None
    print(eq10_text(eq10(obs, expected), weights), end="")
    return 0
