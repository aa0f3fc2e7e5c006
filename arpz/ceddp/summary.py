"""The CEDDP's summary: what each robot says it did, reconciled with what arrived here.

Pure functions over the ingest's per-topic metrics and the robots' own reports. The identities
they make checkable (and that the demo, the tests and the experiments check) are, per topic:
``produced == sent + held_back + write_failures`` (the robot's side) and
``sent == received + lost`` (the network's side), where ``lost`` counts every sample that did not
arrive, whatever the cause: sequence gaps, the tail after the last arrival, and what a writer sent
before this CEDDP was listening.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgspec

from arpz.ceddp.ingest import Ingest, TopicMetrics
from arpz.ceddp.qos_control import QosController
from arpz.messages import RobotStats, writer_id
from arpz.percentiles import Distribution, percentile

#: per-robot totals: the sum of these over the robot's sensor topics (not the Hello probe)
TOTALS = (
    "produced",
    "sent",
    "held_back",
    "write_failures",
    "retransmitted",
    "received",
    "cc_discarded",
    "cc_passed",
    "lost",
    "decode_errors",
)


@dataclass(frozen=True)
class RobotReport:
    """What the CEDDP knows of a robot besides its topics."""

    alive: bool
    joins: int
    leaves: int
    control_decode_errors: int
    stats: RobotStats | None


def topic_summary(ingest: Ingest, m: TopicMetrics, stats: RobotStats | None) -> dict[str, Any]:
    cc = ingest.cache_counters(m.robot, m.topic)
    counters = stats.topics.get(m.topic) if stats else None
    tail_lost = 0
    if stats is not None and stats.final and counters is not None:
        # samples sent after the last one that arrived: invisible as a gap, but lost
        last = Ingest.highest_seq(m, writer_id(m.robot, stats.incarnation))
        tail_lost = max(counters.last_seq - last, 0)
    return {
        "produced": counters.produced if counters else 0,
        "sent": counters.sent if counters else 0,
        "held_back": counters.held_back if counters else 0,
        "write_failures": counters.write_failures if counters else 0,
        "retransmitted": counters.retransmitted if counters else 0,
        "gapped": counters.gapped if counters else 0,
        "overwritten_unacked": counters.overwritten_unacked if counters else 0,
        "received": m.received,
        "cc_discarded": cc.hits,
        "cc_passed": cc.misses,
        "lost": m.lost + tail_lost + m.before_join,
        "out_of_order": m.out_of_order,
        "writer_changes": m.writer_changes,
        "before_join": m.before_join,
        "decode_errors": m.decode_errors,
        "latency_ms_p50": m.latency_ms.quantile(50),
        "latency_ms_p99": m.latency_ms.quantile(99),
    }


def robot_summary(ingest: Ingest, robot: str, report: RobotReport) -> dict[str, Any]:
    """Call with ``ingest.lock`` held."""
    stats = report.stats
    mine = sorted((t, m) for (r, t), m in ingest.topics.items() if r == robot)
    topics = {topic: topic_summary(ingest, m, stats) for topic, m in mine}
    sensors = [row for topic, row in topics.items() if topic != "hello"]
    latencies = [m.latency_ms for topic, m in mine if topic != "hello"]
    return {
        "alive": report.alive,
        "control_decode_errors": report.control_decode_errors,
        "joins": report.joins,
        "leaves": report.leaves,
        "final_stats": bool(stats and stats.final),
        **{key: sum(row[key] for row in sensors) for key in TOTALS},
        "latency_ms_p50": merged_quantile(latencies, 50),
        "latency_ms_p99": merged_quantile(latencies, 99),
        "cpu_percent": stats.cpu_percent if stats else None,
        "hello": msgspec.to_builtins(stats.hello) if stats and stats.hello else None,
        "topics": topics,
    }


def qos_summary(qos: QosController) -> dict[str, Any]:
    return {
        "assignments": [msgspec.to_builtins(m) for m in qos.history],
        "acks": {robot: msgspec.to_builtins(a) for robot, a in qos.acks.items()},
        "refusals": [msgspec.to_builtins(a) for a in qos.refusals],
        "errors": list(qos.errors),
    }


def merged_quantile(distributions: list[Distribution], q: float) -> float | None:
    values: list[float] = []
    for dist in distributions:
        values.extend(dist.sample())
    return percentile(values, q)
