"""The public surface of arpz.configure is what ``__all__`` says, sorted, and importable."""

from __future__ import annotations

import arpz.configure as configure


def _isort_key(name: str) -> tuple[int, str]:
    """ruff's RUF022 order: CONSTANTS, then Classes, then functions."""
    return (0 if name.isupper() else 1 if name[0].isupper() else 2, name)


def test_all_is_sorted_and_every_name_exists():
    assert configure.__all__ == sorted(configure.__all__, key=_isort_key)
    for name in configure.__all__:
        assert hasattr(configure, name), name


def test_public_names_are_exported():
    public = {n for n in dir(configure) if not n.startswith("_")}
    modules = {
        "apply",
        "casestudy",
        "eq10",
        "plan",
        "characterise",
        "check",
        "exact",
        "figure5",
        "greedy",
        "improved",
        "model",
        "problem",
        "regression",
        "report",
        "solution",
        "state",
        "annotations",
        "Literal",
    }
    assert public - modules - set(configure.__all__) == set()
