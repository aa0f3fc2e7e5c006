"""The paper's Figure 5 redone: each method's objective relative to the exact optimum.

The paper normalised its greedy to a brute-force optimum on instances 1-6 only ("several hours"
of brute force); with the MILP every instance gets an exact reference, so the comparison also
covers instances 7-10 and fleets of tens of robots, where the greedy's "within 1 %" stops holding.
Every solution is passed through the independent checker before it is counted.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from arpz.configure import exact, greedy, improved
from arpz.configure.casestudy import INSTANCES, case_study
from arpz.configure.check import check
from arpz.configure.model import Model
from arpz.configure.problem import Problem, ProblemKind
from arpz.configure.solution import Solution


@dataclass
class Row:
    label: str
    problem: int
    nodes: int
    solutions: dict[str, Solution] = field(default_factory=dict)

    def ratio(self, method: str) -> float | None:
        """Objective / exact objective (Problem 1: <= 1 is worse; Problem 2: >= 1 is worse)."""
        ref = self.solutions["exact"].objective
        got = self.solutions[method].objective
        if ref is None or got is None or ref == 0:
            return None
        return got / ref


def compare(model: Model, label: str, kind: ProblemKind, *, time_limit_s: float = 60.0) -> Row:
    problem = Problem.build(model, kind)
    row = Row(label=label, problem=kind, nodes=len(model.nodes))
    row.solutions["greedy"] = greedy.solve(problem)
    row.solutions["greedy-literal"] = greedy.solve(problem, reading="literal")
    row.solutions["improved"] = improved.solve(problem, time_budget_s=min(time_limit_s, 20.0))
    row.solutions["exact"] = exact.solve(problem, time_limit_s=time_limit_s)
    for method, solution in row.solutions.items():
        errors = check(model, solution)
        if errors:
            raise AssertionError(f"{label} P{kind} {method} is infeasible: {errors[:3]}")
    return row


def instances(
    numbers: Sequence[int], fleets: Sequence[tuple[int, int, int]] = ()
) -> list[tuple[str, Model]]:
    """Paper instances by number, plus (robots, cameras, computers) fleets."""
    out = []
    for number in numbers:
        computers, robots, cameras = INSTANCES[number - 1]
        out.append((f"{number}", case_study(robots, cameras, computers)))
    for robots, cameras, computers in fleets:
        out.append((f"{robots}r/{cameras}k/{computers}c", case_study(robots, cameras, computers)))
    return out


def run(
    models: list[tuple[str, Model]],
    problems: Sequence[ProblemKind] = (1, 2),
    *,
    time_limit_s: float = 60.0,
    progress: Callable[[str], None] | None = None,
) -> list[Row]:
    rows = []
    for label, model in models:
        for kind in problems:
            row = compare(model, label, kind, time_limit_s=time_limit_s)
            rows.append(row)
            if progress is not None:
                progress(format_row(row))
    return rows


def _fmt(value: float | None, digits: int = 4) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


HEADER = (
    "| instance | P | nodes | exact | status | gap | greedy/exact | greedy literal/exact "
    "| improved/exact | t greedy s | t improved s | t exact s |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def format_row(row: Row) -> str:
    ex = row.solutions["exact"]
    gap = "-" if ex.gap is None else f"{100 * ex.gap:.3f} %"
    return (
        f"| {row.label} | {row.problem} | {row.nodes} | {_fmt(ex.objective, 3)} | {ex.status} "
        f"| {gap} | {_fmt(row.ratio('greedy'))} | {_fmt(row.ratio('greedy-literal'))} "
        f"| {_fmt(row.ratio('improved'))} "
        f"| {row.solutions['greedy'].solve_time_s:.3f} "
        f"| {row.solutions['improved'].solve_time_s:.3f} | {ex.solve_time_s:.2f} |"
    )


def table(rows: list[Row]) -> str:
    return HEADER + "\n" + "\n".join(format_row(r) for r in rows) + "\n"


def draw(rows: list[Row], path: str) -> None:
    """Grouped bars per instance, one panel per problem, exact = 1 as in the paper's Figure 5."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = sorted({r.problem for r in rows})
    fig, axes = plt.subplots(len(kinds), 1, figsize=(10, 3.6 * len(kinds)), squeeze=False)
    for ax, kind in zip(axes[:, 0], kinds, strict=True):
        sel = [r for r in rows if r.problem == kind]
        xs = range(len(sel))
        width = 0.38
        for offset, method, colour in (
            (-width / 2, "greedy", "#d95f02"),
            (width / 2, "improved", "#1b9e77"),
        ):
            values = [r.ratio(method) or 0.0 for r in sel]
            ax.bar([x + offset for x in xs], values, width, label=method, color=colour)
        ax.axhline(1.0, color="black", linewidth=1, label="exact (MILP)")
        ax.set_xticks(list(xs))
        ax.set_xticklabels([r.label for r in sel], rotation=20)
        ratios = [r.ratio(m) for r in sel for m in ("greedy", "improved")]
        finite = [v for v in ratios if v is not None]
        if kind == 1:
            ax.set_ylim(min([*finite, 0.9]) - 0.02, 1.01)
            ax.set_title("Problem 1: weighted performance / optimum (higher is better)")
        else:
            ax.set_ylim(0.98, max([*finite, 1.02]) + 0.02)
            ax.set_title("Problem 2: server capacity / optimum (lower is better)")
        ax.set_xlabel("instance (1-6: paper's Table II; then larger)")
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
