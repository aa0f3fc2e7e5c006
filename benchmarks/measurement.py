"""What a suite entry is and what it measures: the types the entries (benchmarks/entries.py) and
the suite's runner (benchmarks/suite.py) share, apart from both so neither imports the other."""

from __future__ import annotations

import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Entry:
    """A suite entry: ``run(quick)`` measures it once and returns its ratios by name (every
    name of ``ratios``, whose values say which way is better)."""

    name: str
    what: str
    ratios: dict[str, str]
    run: Callable[[bool], Measurement]
    #: about how long a full measurement takes on the 2-core VM, seconds (for --list)
    seconds: float = 0.0


@dataclass
class Measurement:
    ratios: dict[str, float]
    #: what else a reader wants beside the ratios (absolute figures, counts), one line each
    details: list[str] = field(default_factory=list)


def median_ratio(ours: Sequence[float], theirs: Sequence[float]) -> float:
    """The median of the rounds' own ratios (each round's pair shares a window of the host;
    the ratio of two medians may pair a fast round with a slow one). NaN if none."""
    values = [a / b for a, b in zip(ours, theirs, strict=True) if b]
    return statistics.median(values) if values else float("nan")
