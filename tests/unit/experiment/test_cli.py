"""The command line: presets and spec files, errors with exit code 2, --list, report."""

from __future__ import annotations

from pathlib import Path

import pytest

from arpz.experiment.__main__ import main


def test_list_shows_the_cells_of_a_preset(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "quick", "--out", "unused", "--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 6
    assert lines[0] == "Rmax 1000 Hz, depth 1, baseline, lan, repeat 1"


def test_bad_spec_exits_2_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = tmp_path / "bad.toml"
    spec.write_text('name = "b"\nrmax_hz = [100]\ndepths = [1]\nconfigs = ["xx"]\n')
    assert main(["run", str(spec), "--out", str(tmp_path / "o")]) == 2
    assert "unknown configuration feature 'xx'" in capsys.readouterr().err
    assert main(["run", "no-such-preset", "--out", str(tmp_path / "o")]) == 2
    assert "neither a preset" in capsys.readouterr().err


def test_report_without_results_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report", str(tmp_path)]) == 2
    assert "no results" in capsys.readouterr().err
