"""Solutions as text and as JSON for the CLI (one place, so both say the same thing)."""

from __future__ import annotations

from typing import Any

from arpz.configure.check import check, loads
from arpz.configure.model import Model
from arpz.configure.regression import fit
from arpz.configure.solution import Solution


def curves(model: Model) -> dict[str, dict[str, Any]]:
    """The fitted curve of every node with a continuum: kind, R^2, equation, CPU range."""
    out: dict[str, dict[str, Any]] = {}
    for node in model.nodes:
        if node.continuum is None:
            continue
        cpu = [s.cpu for s in node.settings]
        curve = fit(cpu, [s.performance for s in node.settings], node.continuum.fit)
        out[node.name] = {
            "fit": curve.kind,
            "r2": round(curve.r2, 6),
            "equation": curve.equation(),
            "cpu": [min(cpu), max(cpu)],
            "step": node.continuum.step,
        }
    return out


def as_dict(model: Model, solution: Solution) -> dict[str, Any]:
    measured = loads(model, solution)
    mapped = {n.name: n for n in model.nodes}
    capacity = {c.name: c.capacity for c in model.computers}
    capacity.update(solution.server_capacity)
    bandwidth = {f"{lk.between[0]} - {lk.between[1]}": lk.bandwidth for lk in model.links}
    return {
        "problem": solution.problem,
        "method": solution.method,
        "status": solution.status,
        "objective": solution.objective,
        "gap": solution.gap,
        "bound": solution.bound,
        "solve_time_s": round(solution.solve_time_s, 4),
        "message": solution.message,
        "assignment": {
            name: {
                "computer": p.computer,
                "cpu": p.cpu,
                "performance": p.performance,
                "parameter": p.parameter,
                "frequency_hz": p.frequency_hz,
                "bandwidth": p.bandwidth,
            }
            for name, p in solution.assignment.items()
        },
        #: what ``apply`` needs without the model: each node's weight, where it runs and what
        #: in arpz it is
        "nodes": {
            name: {
                "weight": mapped[name].weight,
                "on": _kind(model, p.computer),
                "topic": mapped[name].topic,
                "computation": mapped[name].computation,
            }
            for name, p in solution.assignment.items()
            if name in mapped
        },
        "computers": {
            name: {"load": round(load, 6), "capacity": capacity[name]}
            for name, load in measured.computer.items()
        }
        if solution.assignment
        else {},
        "links": {
            name: {"load": round(load, 6), "bandwidth": bandwidth[name]}
            for name, load in measured.link.items()
        }
        if solution.assignment
        else {},
        "server_capacity": solution.server_capacity,
        "curves": curves(model),
        "violations": check(model, solution),
    }


def _kind(model: Model, computer: str) -> str:
    return next((c.kind for c in model.computers if c.name == computer), "")


def _num(value: float | None) -> str:
    return "-" if value is None else f"{value:g}"


def as_text(model: Model, solution: Solution) -> str:
    data = as_dict(model, solution)
    what = "weighted performance" if solution.problem == 1 else "total server capacity"
    lines = [f"problem {solution.problem} ({what}), method {solution.method}"]
    lines.append(f"status     {solution.status}")
    if solution.objective is None:
        lines.append(f"no solution: {solution.message}")
        lines.append(f"solve time {solution.solve_time_s:.3f} s")
        return "\n".join(lines) + "\n"
    lines.append(f"objective  {solution.objective:.4f}")
    if solution.gap is not None:
        bound = f"{solution.bound:.4f}" if solution.bound is not None else "-"
        lines.append(f"gap        {100 * solution.gap:.4f} % (bound {bound})")
    lines.append(f"solve time {solution.solve_time_s:.3f} s")
    if solution.message:
        lines.append(f"note       {solution.message}")
    lines.append("")
    width = max(len(n) for n in data["assignment"]) if data["assignment"] else 4
    lines.append(
        f"{'node':<{width}}  {'computer':<12} {'cpu':>8} {'performance':>12} {'parameter':>10} "
        f"{'Hz':>7} {'bandwidth':>9}"
    )
    for name, p in data["assignment"].items():
        lines.append(
            f"{name:<{width}}  {p['computer']:<12} {p['cpu']:>8g} {p['performance']:>12g} "
            f"{_num(p['parameter']):>10} {_num(p['frequency_hz']):>7} {_num(p['bandwidth']):>9}"
        )
    lines.append("")
    lines.append(f"{'computer':<12} {'load':>8} {'capacity':>9}")
    for name, c in data["computers"].items():
        lines.append(f"{name:<12} {c['load']:>8g} {c['capacity']:>9g}")
    if data["links"]:
        lines.append("")
        lines.append(f"{'link':<24} {'load':>8} {'bandwidth':>10}")
        for name, lk in data["links"].items():
            lines.append(f"{name:<24} {lk['load']:>8g} {lk['bandwidth']:>10g}")
    if data["curves"]:
        lines.append("")
        lines.append(f"{'curve of':<{width}}  {'fit':<6} {'R^2':>8}  equation (x = cpu / 100)")
        for name, c in data["curves"].items():
            lines.append(f"{name:<{width}}  {c['fit']:<6} {c['r2']:>8.5f}  {c['equation']}")
    if data["violations"]:
        lines.append("")
        lines.append("VIOLATIONS (a solver bug):")
        lines.extend(f"  {v}" for v in data["violations"])
    return "\n".join(lines) + "\n"
