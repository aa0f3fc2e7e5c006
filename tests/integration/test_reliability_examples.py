"""The examples run and say what they promise."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


def test_reliable_fleet_example() -> None:
    out = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "reliable_fleet.py")],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert out.returncode == 0, out.stderr
    assert "arpz/demo/robot/r1/sensor/dht11: 100 samples, in order: True" in out.stdout
    assert "arpz/demo/robot/r2/sensor/dht11: 3 samples, in order: True" in out.stdout
    assert "deadline missed" not in out.stdout
    assert "unchanged=97" in out.stdout
