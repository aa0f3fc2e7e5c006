"""Which arpz, which Zenoh: what ``--version`` prints and what robots and the CEDDP report about
themselves. Read from the installed distributions' metadata, never imported from zenoh, so that
the contracts layer stays free of it."""

from __future__ import annotations

import platform
from importlib import metadata


def distribution_version(name: str) -> str:
    """The installed version of a distribution, or "not installed"."""
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def arpz_version() -> str:
    return distribution_version("arpz")


def zenoh_version() -> str:
    return distribution_version("eclipse-zenoh")


def version_line() -> str:
    return (
        f"arpz {arpz_version()} (eclipse-zenoh {zenoh_version()}, "
        f"Python {platform.python_version()})"
    )
