"""What every test on the kernel lab needs first: root, ``nft`` and namespaces. Where they are
missing the test skips with the reason, unless ``ARPZ_REQUIRE_LAB=1`` (CI, which runs as root)
turns the skip into a failure: a lab test that quietly skipped in CI would prove nothing."""

from __future__ import annotations

import os

import pytest

from arpz.lab import LabUnavailable, check_available


def require_lab() -> None:
    try:
        check_available()
    except LabUnavailable as exc:
        if os.environ.get("ARPZ_REQUIRE_LAB") == "1":
            pytest.fail(f"ARPZ_REQUIRE_LAB=1 but the lab cannot run here: {exc}")
        pytest.skip(str(exc))
