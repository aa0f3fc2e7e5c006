"""Least-squares curves from a few characterised settings to a continuum of settings.

The paper (seed 002, Section IV-B) characterises each configurable node at three or four
settings and interpolates the rest by regression; the authors' code samples the fitted curve at
every integer CPU step between the smallest and largest characterised CPU and rounds the
performance to 2 decimals. ``x`` is the CPU utilisation divided by 100, as in the paper's fitted
equations, so the coefficients printed here read like theirs (``P = 66.62 ln x + 56.308``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from arpz.errors import ArpzError

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
    """A fitted curve P(U). ``coefficients`` are highest power first, in x = U / 100."""

    kind: Kind
    coefficients: tuple[float, ...]
    r2: float

    def __call__(self, cpu: float) -> float:
        x = cpu / 100.0
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


def fit(cpu: Sequence[float], performance: Sequence[float], kind: FitChoice) -> Curve:
    """Fit one curve kind (or the best by R^2) to (CPU, performance) points."""
    if kind == "best":
        return best_fit(cpu, performance)
    xs = np.asarray(cpu, dtype=float) / 100.0
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
    return Curve(kind, tuple(float(c) for c in coef), r2)


def candidate_fits(cpu: Sequence[float], performance: Sequence[float]) -> list[Curve]:
    """Every curve kind the points can support, in ``KINDS`` order."""
    curves: list[Curve] = []
    for kind in KINDS:
        try:
            curves.append(fit(cpu, performance, kind))
        except FitError:
            continue
    return curves


def best_fit(cpu: Sequence[float], performance: Sequence[float]) -> Curve:
    """The curve with the highest R^2; ties go to the simpler curve.

    With three points a parabola interpolates exactly (R^2 = 1), so "best" picks poly2 for any
    three-setting node whose points are not exactly linear or logarithmic; name the curve in the
    model when the shape is known (the paper's Tracker, Model and Navigation are logarithmic).
    """
    curves = candidate_fits(cpu, performance)
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
