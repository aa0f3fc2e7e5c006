"""One error root: every exception class arpz defines is an ``ArpzError`` (issue 16), so a caller
can catch what arpz raises on purpose without ``except Exception``."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import arpz
from arpz.core.errors import ArpzError


def _arpz_modules() -> list[str]:
    """Every module of the package (the test extra installs the server extra's imports too)."""
    return [m.name for m in pkgutil.walk_packages(arpz.__path__, "arpz.")]


def test_every_exception_arpz_defines_derives_from_arpz_error() -> None:
    strays: list[str] = []
    seen = 0
    for name in _arpz_modules():
        if name.endswith("__main__"):
            continue
        module = importlib.import_module(name)
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if cls.__module__ != name or not issubclass(cls, BaseException):
                continue
            seen += 1
            if not issubclass(cls, ArpzError):
                strays.append(f"{name}.{cls.__qualname__}")
    assert seen >= 15, seen  # the walk found the package's errors at all
    assert strays == [], strays
