"""The layers of docs/architecture.md at run time: import-linter (CI) checks the import
statements; this checks what importing a module really loads, package ``__init__`` files
included, in a fresh interpreter."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

#: the bottom layers: usable (and unit-testable) with no Zenoh, no Rerun, no solver loaded
PURE = [
    "arpz.core.protocol.reader_machine",
    "arpz.core.protocol.writer_machine",
    "arpz.channel",
    "arpz.core.config",
    "arpz.core.messages",
    "arpz.core.frames",
    "arpz.transport.memory",
    "arpz.mission",
    "arpz.channel.io",
    "arpz.core.link_sizes",
]


def _loaded_after(module: str) -> set[str]:
    code = f"import sys, json, {module}; print(json.dumps(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return {name.split(".")[0] for name in json.loads(out.stdout)}


@pytest.mark.parametrize("module", PURE)
def test_the_contracts_layer_loads_no_zenoh_rerun_or_solver(module: str) -> None:
    assert not _loaded_after(module) & {"zenoh", "rerun", "cvxpy", "highspy"}, module


def test_the_robot_entry_point_loads_nothing_of_the_server_extra() -> None:
    loaded = _loaded_after("arpz.robot.__main__")
    assert "zenoh" in loaded  # it did import the robot's runtime
    assert not loaded & {"rerun", "cvxpy", "highspy", "matplotlib", "scipy"}
