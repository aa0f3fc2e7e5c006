"""Every example of docs/api.md and docs/nodes.md runs as written (from the repository root, as
a reader would)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BLOCKS = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "api.md").read_text(), re.S)
NODES = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "nodes.md").read_text(), re.S)


def test_the_api_page_has_an_example_for_each_part() -> None:
    assert len(BLOCKS) >= 8, len(BLOCKS)


@pytest.mark.parametrize(
    "code",
    BLOCKS + NODES,
    ids=[f"api{i + 1}" for i in range(len(BLOCKS))] + [f"nodes{i + 1}" for i in range(len(NODES))],
)
def test_the_example_runs(code: str) -> None:
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stdout + result.stderr
