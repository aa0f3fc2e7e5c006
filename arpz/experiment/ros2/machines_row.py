"""The results.csv row of a ROS 2 cell, from the counters its nodes wrote: the same columns as
an arpz cell's row (``arpz.experiment.results.row_from_summary``), so the report puts both
middlewares side by side.

Pure: counters in, a row out (no rclpy, no lab), so the reconciliation is unit-tested.
``samples_lost`` is what the publishers sent and the CEDDP never took (sequence numbers per
topic, duplicates not counted twice), so sent = received + lost holds by construction; a CEDDP
that took more of a topic than its robot says it sent is an error, not a negative loss.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from arpz.core.errors import ArpzError
from arpz.experiment.results import cell_identity, cpu_columns, hello_columns
from arpz.experiment.spec import Cell


class CountersError(ArpzError, ValueError):
    """Counters that do not reconcile or miss a part: the cell is an error row."""


@dataclass(frozen=True)
class CellCounters:
    """What a ROS 2 cell measured: every node's JSON (``ceddp``, ``robot1``...), the CPU of
    each process over the window, and the lab's link counters."""

    nodes: dict[str, dict[str, Any]]
    cpu_s: dict[str, float]
    link_seen: int
    link_dropped: int
    #: bytes robot -> access point (what the samples cross)
    bytes_up: int
    measured_s: float
    wall_s: float
    rate_hz: float
    depth: int


def _pct(part: float, whole: float) -> float | None:
    return 100.0 * part / whole if whole else None


def ros2_row(cell: Cell, counters: CellCounters, *, experiment: str) -> dict[str, Any]:
    """The row of a finished ROS 2 cell. Raises CountersError when a node's counters miss or
    do not reconcile."""
    ceddp = counters.nodes.get("ceddp")
    if ceddp is None:
        raise CountersError("the CEDDP node wrote no counters")
    robots = {name: c for name, c in counters.nodes.items() if name != "ceddp"}
    intake = ceddp.get("robots") or {}
    produced = sent = received = 0
    p50s: list[float] = []
    p99s: list[float] = []
    rates: list[float] = []
    for name, robot in robots.items():
        taken = intake.get(name)
        if taken is None:
            raise CountersError(f"the CEDDP has no counters for {name}")
        for topic, published in (robot.get("topics") or {}).items():
            got = int(((taken.get("topics") or {}).get(topic) or {}).get("received") or 0)
            if got > int(published["sent"]):
                raise CountersError(
                    f"{name}/{topic}: the CEDDP took {got} samples, the robot sent "
                    f"{published['sent']}"
                )
            produced += int(published["produced"])
            sent += int(published["sent"])
            received += got
            if robot.get("window_s"):
                rates.append(int(published["sent"]) / float(robot["window_s"]))
        if taken.get("latency_ms_p50") is not None:
            p50s.append(float(taken["latency_ms_p50"]))
            p99s.append(float(taken["latency_ms_p99"]))
    origin = next((r for r in robots.values() if r.get("hello")), None)
    hello = (origin or {}).get("hello") or {}
    written = sum(int(v) for v in (ceddp.get("hops_written") or {}).values())
    delivered = sum(int(r.get("hops_received") or 0) for r in robots.values())
    lost = sent - received
    return {
        **cell_identity(cell, experiment),
        "status": "ok",
        **hello_columns(hello),
        "sample_latency_ms_p50": max(p50s) if p50s else None,
        "sample_latency_ms_p99": max(p99s) if p99s else None,
        "sample_loss_pct": _pct(lost, sent),
        "samples_produced": produced,
        "samples_sent": sent,
        "samples_held_back": 0,
        "samples_write_failures": 0,
        "samples_received": received,
        "samples_lost": lost,
        "final_reports": len(robots),
        "rate_hz": counters.rate_hz,
        "rate_hz_achieved": sum(rates) / len(rates) if rates else None,
        "qos_depth": counters.depth,
        "deadline_ms": 1000.0 / counters.rate_hz,
        "qos_epochs": 0,
        "qos_applied": 0,
        "hello_hops_written": written,
        "hello_hops_delivered": delivered,
        "hello_hops_lost": written - delivered,
        "downlink_reconciled": "yes" if delivered <= written else "no",
        "downlink_unreconciled": "" if delivered <= written else "hello",
        **cpu_columns(counters.cpu_s),
        "link_datagrams": counters.link_seen,
        "link_dropped": counters.link_dropped,
        "link_loss_pct": _pct(counters.link_dropped, counters.link_seen),
        "link_bytes_up": counters.bytes_up,
        "measured_s": counters.measured_s,
        "wall_s": counters.wall_s,
        "rrd": "",
    }
