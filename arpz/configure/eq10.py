"""Eq. 10 of seed 002 on the quantity the paper reports: the overall weighted performance.

The paper estimates each node's real performance from its observed message frequency,
P_measured = P_expected x F_measured / F_expected (eq. 10), and compares the configuration's
overall performance, sum(w_n P_n), measured against expected (Fig. 5: "measured performance
values only deviate by 2.5 % on average from the expected ones", the average over its instances).
``summarise`` computes that comparison for one running configuration, so the figure printed next
to the paper's is the same quantity: the relative difference of the weighted sums, not a mean of
per-topic deviations.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

#: the paper's figure, for the reports (Section V-C)
PAPER_DEVIATION_PERCENT = 2.5


@dataclass(frozen=True)
class Eq10Node:
    """One node's expected and observed frequency, and its expected performance and weight."""

    name: str
    weight: float
    p_expected: float
    f_expected_hz: float
    f_measured_hz: float

    @property
    def p_measured(self) -> float:
        """Eq. 10; a node expected to send nothing keeps its expected performance."""
        if self.f_expected_hz <= 0:
            return self.p_expected
        return self.p_expected * self.f_measured_hz / self.f_expected_hz

    @property
    def deviation(self) -> float:
        """(P_measured - P_expected) / P_expected (0 when nothing was expected)."""
        return (self.p_measured - self.p_expected) / self.p_expected if self.p_expected else 0.0


@dataclass(frozen=True)
class Eq10Summary:
    nodes: tuple[Eq10Node, ...]
    #: sum(w P_expected) and sum(w P_measured) over the nodes
    expected: float
    measured: float

    @property
    def deviation(self) -> float:
        """(measured - expected) / expected: the quantity of the paper's 2.5 %."""
        return (self.measured - self.expected) / self.expected if self.expected else 0.0


def summarise(nodes: Sequence[Eq10Node]) -> Eq10Summary:
    return Eq10Summary(
        nodes=tuple(nodes),
        expected=sum(n.weight * n.p_expected for n in nodes),
        measured=sum(n.weight * n.p_measured for n in nodes),
    )


def summary_text(summary: Eq10Summary) -> str:
    """The table of nodes and the overall comparison, for the CLI."""
    if not summary.nodes:
        return "eq. 10: no node with an expected frequency was measured\n"
    width = max(12, *(len(n.name) for n in summary.nodes))
    lines = [
        f"{'node':<{width}} {'weight':>7} {'F exp Hz':>9} {'F meas Hz':>9} {'P exp':>8} "
        f"{'P meas':>8} {'dev %':>7}"
    ]
    for n in summary.nodes:
        lines.append(
            f"{n.name:<{width}} {n.weight:>7.4f} {n.f_expected_hz:>9.2f} {n.f_measured_hz:>9.2f}"
            f" {n.p_expected:>8.2f} {n.p_measured:>8.2f} {100 * n.deviation:>7.1f}"
        )
    lines.append(
        f"overall sum(w P): expected {summary.expected:.3f}, measured {summary.measured:.3f}, "
        f"deviation {100 * summary.deviation:+.2f} % (the quantity of the paper's Fig. 5, whose "
        f"measured values deviate {PAPER_DEVIATION_PERCENT} % on average over its instances)"
    )
    return "\n".join(lines) + "\n"
