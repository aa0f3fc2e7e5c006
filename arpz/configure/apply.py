"""``python -m arpz.configure apply``: push a solution to a running fleet and measure it (RQ3).

1. the input is a model file (solved here, ``--problem``/``--method``) or the JSON a ``solve
   --json`` printed; ``plan`` turns it into each robot's sensor rates and computation places;
2. a ``ConfigurationMsg`` goes out on ``arpz/{fleet}/ceddp/config`` through the reliable channel
   (TRANSIENT_LOCAL, like the QoS assignment: a robot that joins during the run gets it too);
3. every robot of the plan answers on ``robot/{robot}/config/ack`` with what it runs now; a robot
   that does not answer within ``--ack-timeout`` is an error (exit 1), as is a refusal;
4. after ``--settle`` seconds (the robots' stats average over their report period, so the first
   report after the change mixes old and new rates) the fleet's reports are heard for
   ``--duration`` seconds and eq. 10 compares expected with measured performance
   (arpz/configure/eq10.py), with F_measured per topic as ``characterise`` counts it: arrived at
   the CEDDP plus held back unchanged by the robot's local cache.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path
from typing import Any

from arpz.configure.characterise import held_back_rates, listen, measured_rates
from arpz.configure.eq10 import summarise, summary_text
from arpz.configure.model import ModelError, load_model
from arpz.configure.plan import Plan, eq10_nodes, plan
from arpz.configure.report import as_dict
from arpz.core import keys
from arpz.core.errors import ArpzError
from arpz.core.messages import (
    CONFIGURATION_ACK_DECODER,
    DECODE_ERRORS,
    ConfigurationAck,
    encode,
    new_incarnation,
)
from arpz.core.traffic import ASSIGNMENT_QOS, REPORT_QOS
from arpz.runtime.startup import JSON_TO_STDOUT, connect_endpoints, emit_json, fail

TOOL = "configure apply"


def load_solution(path: str, *, problem: int, method: str, time_limit_s: float) -> dict[str, Any]:
    """A solution's JSON object: read as is, or solved from a model file."""
    file = Path(path)
    if file.suffix.lower() == ".json":
        try:
            data = json.loads(file.read_text())
        except (OSError, ValueError) as exc:
            raise ModelError(f"{path}: cannot read: {exc}") from exc
        if isinstance(data, dict) and "assignment" in data:
            return data
    from arpz.configure import solve

    model = load_model(file)
    solution = solve(model, problem=problem, method=method, time_limit_s=time_limit_s)  # type: ignore[arg-type]
    return as_dict(model, solution)


class AckWaiter:
    """Collects the robots' answers (on the channel's thread: only store under a lock)."""

    def __init__(self, epoch: int, sender: str) -> None:
        self.epoch = epoch
        self.sender = sender
        self.acks: dict[str, ConfigurationAck] = {}
        self.undecodable = 0
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)

    def on_message(self, _key: str, payload: bytes) -> None:
        try:
            ack = CONFIGURATION_ACK_DECODER.decode(payload)
        except DECODE_ERRORS:
            with self._lock:
                self.undecodable += 1
            return
        if ack.sender != self.sender or ack.epoch != self.epoch:
            return  # an answer to another configuration (latched, or another configurator)
        with self._changed:
            self.acks[ack.robot] = ack
            self._changed.notify_all()

    def wait(self, robots: set[str], timeout_s: float) -> dict[str, ConfigurationAck]:
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while not robots <= set(self.acks):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._changed.wait(left)
            return dict(self.acks)


def check_acks(planned: Plan, acks: dict[str, ConfigurationAck]) -> list[str]:
    """What the fleet did not do as planned: missing answers, refusals, other rates or places."""
    problems: list[str] = []
    for robot in sorted(
        {t.robot for t in planned.topics} | {c.robot for c in planned.computations}
    ):
        ack = acks.get(robot)
        if ack is None:
            problems.append(f"{robot}: no answer (is it running, in fleet and mode?)")
            continue
        problems += [f"{robot}: refused {reason}" for reason in ack.refused]
        for t in planned.topics:
            if t.robot == robot and abs(ack.rates_hz.get(t.topic, -1.0) - t.rate_hz) > 1e-9:
                problems.append(f"{robot}/{t.topic}: runs at {ack.rates_hz.get(t.topic)} Hz")
        for c in planned.computations:
            if c.robot == robot and ack.computations.get(c.name) != c.place:
                problems.append(f"{robot}/{c.name}: runs on {ack.computations.get(c.name)}")
    return problems


def main(args: argparse.Namespace) -> int:
    from arpz.channel.io import Inlet, Outlet
    from arpz.core.transport import SessionSettings, TransportError
    from arpz.transport.zenoh import ZenohTransport

    try:
        solution = load_solution(
            args.input, problem=args.problem, method=args.method, time_limit_s=args.time_limit
        )
        planned = plan(solution)
        keys.fleet_prefix(args.fleet)
        endpoints = connect_endpoints(args.connect)
    except (ArpzError, ValueError) as exc:
        return fail(TOOL, str(exc))
    channel = args.reliability == "channel"
    sender = f"configure-{new_incarnation()}"
    epoch = time.time_ns()  # grows across runs of the tool, so a robot can tell newer ones
    message = planned.message(
        sender=sender,
        epoch=epoch,
        stamp_ns=time.time_ns(),
        source=f"{args.input} (problem {solution.get('problem')}, {solution.get('method')})",
    )
    quiet = args.json == JSON_TO_STDOUT
    try:
        transport = ZenohTransport.open(
            SessionSettings(mode="client", connect=list(endpoints), config_file=args.zenoh_config),
            timeout_s=5.0,
        )
    except TransportError as exc:
        return fail(TOOL, str(exc))
    waiter = AckWaiter(epoch, sender)
    robots = set(message.robots)
    try:
        acks_in = Inlet(
            transport,
            keys.all_config_acks(args.fleet),
            REPORT_QOS if channel else None,
            waiter.on_message,
        )
        out = Outlet(
            transport, keys.ceddp_config_key(args.fleet), ASSIGNMENT_QOS if channel else None
        )
        # a VOLATILE reader misses what was written before it matched; the robots' readers are
        # TRANSIENT_LOCAL, but wait (bounded) so a plain-mode put is not sent into the void
        deadline = time.monotonic() + args.ack_timeout
        while not out.matched and time.monotonic() < deadline:
            time.sleep(0.02)
        out.send(encode(message), message.stamp_ns)
        if not quiet:
            for robot, part in sorted(message.robots.items()):
                rates = ", ".join(f"{t} {r:g} Hz" for t, r in sorted(part.rates_hz.items()))
                places = ", ".join(f"{c} on {p}" for c, p in sorted(part.computations.items()))
                print(f"-> {robot}: {'; '.join(x for x in (rates, places) if x)}", flush=True)
        acks = waiter.wait(robots, args.ack_timeout)
        problems = check_acks(planned, acks)
        if not quiet:
            print(f"{len(acks)} of {len(robots)} robot(s) answered", flush=True)
            for problem in problems:
                print(f"   {problem}")
        obs = None
        if acks and args.duration > 0:
            time.sleep(args.settle)
            obs = listen(transport, args.fleet, args.duration)
        acks_in.close()
        out.close()
    finally:
        transport.close()
    measured: dict[tuple[str, str], float] = {}
    if obs is not None:
        held = held_back_rates(obs)
        for key, (rate, _bps) in measured_rates(obs).items():
            measured[key] = rate + held.get(key, 0.0)
    nodes, missing = eq10_nodes(planned, measured)
    summary = summarise(nodes)
    if not quiet:
        print("F meas = arrived at the CEDDP + held back (unchanged) by the robot's local cache")
        print(summary_text(summary), end="")
        if missing:
            print(f"not measured (counted as 0 Hz): {', '.join(missing)}")
    emit_json(
        {
            "configuration": {
                "epoch": epoch,
                "robots": {
                    r: {"rates_hz": p.rates_hz, "computations": p.computations}
                    for r, p in message.robots.items()
                },
            },
            "acks": {
                r: {"rates_hz": a.rates_hz, "computations": a.computations, "refused": a.refused}
                for r, a in acks.items()
            },
            "problems": problems,
            "eq10": {
                "nodes": [
                    {
                        "node": n.name,
                        "weight": n.weight,
                        "f_expected_hz": n.f_expected_hz,
                        "f_measured_hz": round(n.f_measured_hz, 4),
                        "p_expected": n.p_expected,
                        "p_measured": round(n.p_measured, 4),
                    }
                    for n in nodes
                ],
                "expected": summary.expected,
                "measured": summary.measured,
                "deviation": summary.deviation,
                "not_measured": missing,
            },
        },
        args.json,
    )
    if problems:
        return fail(TOOL, f"{len(problems)} part(s) of the configuration were not applied", 1)
    return 0


def add_parser(sub: Any) -> None:
    from arpz.runtime.startup import add_json_option

    p = sub.add_parser("apply", help="push a solution to a running fleet and measure it (eq. 10)")
    p.add_argument("input", help="a model file (solved here) or a solution's JSON (solve --json)")
    p.add_argument("--connect", required=True, help="Zenoh endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--fleet", default="demo")
    p.add_argument("--zenoh-config", default=None, metavar="FILE")
    p.add_argument("--reliability", choices=("channel", "none"), default="channel")
    p.add_argument("--problem", type=int, choices=(1, 2), default=1)
    p.add_argument("--method", choices=("greedy", "exact", "improved"), default="improved")
    p.add_argument("--time-limit", type=float, default=60.0)
    p.add_argument("--ack-timeout", type=float, default=10.0, help="seconds to wait for robots")
    p.add_argument("--settle", type=float, default=2.0, help="seconds before measuring")
    p.add_argument("--duration", type=float, default=5.0, help="seconds to measure (0: none)")
    add_json_option(p, "the configuration, the acks and eq. 10")
    p.set_defaults(func=main)
