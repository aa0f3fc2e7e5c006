"""Least-squares curves from a few characterised settings to a continuum of settings.

The paper (seed 002, Section IV-B) characterises each configurable node at three or four
settings and interpolates the rest by regression; the authors' code samples the fitted curve at
every integer CPU step between the smallest and largest characterised CPU and rounds the
performance to 2 decimals. ``x`` is the CPU utilisation divided by 100, as in the paper's fitted
equations, so the coefficients printed here read like theirs (``P = 66.62 ln x + 56.308``).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from arpz.core.errors import ArpzError

Kind = Literal["linear", "log", "poly2"]
FitChoice = Literal["linear", "log", "poly2", "best"]

#: Simplest first: "best" keeps the earlier curve when R^2 ties, so three points that a line
#: fits exactly are not reported as a parabola.
KINDS: tuple[Kind, ...] = ("linear", "log", "poly2")
_MIN_POINTS: dict[Kind, int] = {"linear": 2, "log": 2, "poly2": 3}
_TIE = 1e-9


class FitError(ArpzError, ValueError):
    """The points cannot support the requested curve (too few, or a log of a non-positive CPU)."""


@dataclass(frozen=True)
class Curve:
    """A fitted curve y(v). ``coefficients`` are highest power first, in x = v / scale: P(U) with
    x = U / 100 as the paper prints Fig. 4, or y(parameter) with scale 1 for Fig. 3."""

    kind: Kind
    coefficients: tuple[float, ...]
    r2: float
    scale: float = 100.0

    def __call__(self, cpu: float) -> float:
        x = cpu / self.scale
        if self.kind == "linear":
            a, b = self.coefficients
            return a * x + b
        if self.kind == "log":
            a, b = self.coefficients
            return a * math.log(x) + b
        a, b, c = self.coefficients
        return a * x * x + b * x + c

    def equation(self) -> str:
        """The curve as the paper prints its fits, for reports."""
        if self.kind == "linear":
            a, b = self.coefficients
            return f"P = {a:.4g} x {_signed(b)}"
        if self.kind == "log":
            a, b = self.coefficients
            return f"P = {a:.5g} ln x {_signed(b)}"
        a, b, c = self.coefficients
        return f"P = {a:.5g} x^2 {_signed(b, 'x')} {_signed(c)}"


def _signed(value: float, suffix: str = "") -> str:
    sign = "-" if value < 0 else "+"
    tail = f" {suffix}" if suffix else ""
    return f"{sign} {abs(value):.5g}{tail}"


def fit(
    cpu: Sequence[float], performance: Sequence[float], kind: FitChoice, *, scale: float = 100.0
) -> Curve:
    """Fit one curve kind (or the best by R^2) to (CPU, performance) points (or any (v, y)
    points, x = v / scale)."""
    if kind == "best":
        return best_fit(cpu, performance, scale=scale)
    xs = np.asarray(cpu, dtype=float) / scale
    ys = np.asarray(performance, dtype=float)
    distinct = len(set(xs.tolist()))
    if distinct < _MIN_POINTS[kind]:
        raise FitError(
            f"a {kind} fit needs at least {_MIN_POINTS[kind]} distinct CPU values, got {distinct}"
        )
    if kind == "log":
        if np.any(xs <= 0):
            raise FitError("a log fit needs every CPU value > 0")
        design = np.column_stack([np.log(xs), np.ones_like(xs)])
    elif kind == "linear":
        design = np.column_stack([xs, np.ones_like(xs)])
    else:
        design = np.column_stack([xs * xs, xs, np.ones_like(xs)])
    coef, *_ = np.linalg.lstsq(design, ys, rcond=None)
    predicted = design @ coef
    ss_res = float(np.sum((ys - predicted) ** 2))
    ss_tot = float(np.sum((ys - ys.mean()) ** 2))
    r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else 1.0
    return Curve(kind, tuple(float(c) for c in coef), r2, scale)


def candidate_fits(
    cpu: Sequence[float], performance: Sequence[float], *, scale: float = 100.0
) -> list[Curve]:
    """Every curve kind the points can support, in ``KINDS`` order."""
    curves: list[Curve] = []
    for kind in KINDS:
        try:
            curves.append(fit(cpu, performance, kind, scale=scale))
        except FitError:
            continue
    return curves


def best_fit(cpu: Sequence[float], performance: Sequence[float], *, scale: float = 100.0) -> Curve:
    """The curve with the highest R^2; ties go to the simpler curve.

    With three points a parabola interpolates exactly (R^2 = 1), so "best" picks poly2 for any
    three-setting node whose points are not exactly linear or logarithmic; name the curve in the
    model when the shape is known (the paper's Tracker, Model and Navigation are logarithmic).
    """
    curves = candidate_fits(cpu, performance, scale=scale)
    if not curves:
        raise FitError("no curve fits: give at least two settings with distinct CPU values")
    best = curves[0]
    for curve in curves[1:]:
        if curve.r2 > best.r2 + _TIE:
            best = curve
    return best


def expand(
    cpu: Sequence[float], performance: Sequence[float], kind: FitChoice, step: int
) -> tuple[Curve, list[tuple[float, float]]]:
    """Settings at every ``step`` CPU units from the smallest to the largest characterised CPU.

    The largest CPU is always included even when the range is not a multiple of ``step``, so the
    node can still reach its best characterised setting.
    """
    curve = fit(cpu, performance, kind)
    low, high = min(cpu), max(cpu)
    points: list[float] = []
    value = float(low)
    while value < high - 1e-9:
        points.append(value)
        value += step
    points.append(float(high))
    return curve, [(u, round(curve(u), 2)) for u in points]


# -- Fig. 3: a node's CPU and performance as functions of its parameter ---------------------------

_MONOTONE_SAMPLES = 64


def _increasing(curve: Curve, low: float, high: float) -> bool:
    """Strictly increasing on [low, high], sampled: only then can CPU be turned into a parameter."""
    values = [
        curve(low + (high - low) * i / _MONOTONE_SAMPLES) for i in range(_MONOTONE_SAMPLES + 1)
    ]
    return all(b > a for a, b in itertools.pairwise(values))


@dataclass(frozen=True)
class ParameterCurves:
    """A node's Fig. 3 regressions: CPU(parameter) and performance(parameter), in x = parameter.

    The solvers choose a CPU (Fig. 4's axis); ``parameter_at`` inverts CPU(parameter) so a
    solution says which parameter value to run (particles, Hz, goals)."""

    cpu: Curve
    performance: Curve
    low: float
    high: float

    def parameter_at(self, cpu: float) -> float:
        """The parameter whose fitted CPU is ``cpu`` (bisection; clamped to the characterised
        range, where the curve was checked to increase)."""
        lo, hi = self.low, self.high
        if cpu <= self.cpu(lo):
            return lo
        if cpu >= self.cpu(hi):
            return hi
        for _ in range(100):
            mid = (lo + hi) / 2
            if self.cpu(mid) < cpu:
                lo = mid
            else:
                hi = mid
        return (lo + hi) / 2


def parameter_curves(
    parameter: Sequence[float], cpu: Sequence[float], performance: Sequence[float], kind: FitChoice
) -> ParameterCurves:
    """Fit CPU and performance against the parameter. ``best`` keeps, among the CPU curves that
    increase over the characterised range, the one with the highest R^2 (a parabola through
    three points may turn back, and a CPU that falls as the parameter grows cannot be inverted).
    """
    low, high = min(parameter), max(parameter)
    if kind == "best":
        usable = [c for c in candidate_fits(parameter, cpu, scale=1.0) if _increasing(c, low, high)]
        if not usable:
            raise FitError("no CPU-vs-parameter curve increases over the characterised parameters")
        cpu_curve = usable[0]
        for curve in usable[1:]:
            if curve.r2 > cpu_curve.r2 + _TIE:
                cpu_curve = curve
        perf_curve = best_fit(parameter, performance, scale=1.0)
    else:
        cpu_curve = fit(parameter, cpu, kind, scale=1.0)
        if not _increasing(cpu_curve, low, high):
            raise FitError(
                f"the {kind} curve of CPU against the parameter does not increase over "
                f"[{low:g}, {high:g}]: choose another parameter_fit"
            )
        perf_curve = fit(parameter, performance, kind, scale=1.0)
    return ParameterCurves(cpu_curve, perf_curve, low, high)
