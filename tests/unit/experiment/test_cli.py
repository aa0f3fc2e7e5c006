"""The command line: presets and spec files, errors with exit code 2, --list, report."""

from __future__ import annotations

from pathlib import Path

import pytest

from arpz.experiment.__main__ import main


def test_list_shows_the_cells_of_a_preset(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "quick", "--out", "unused", "--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 6
    assert lines[0] == "Rmax 1000 Hz, depth 1, baseline, lan, repeat 1, arpz"


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


def test_paper_grids_have_every_configuration_and_three_repeats(
    capsys: pytest.CaptureFixture[str],
) -> None:
    for preset, cells in (("paper-machines", 336), ("paper-simulation", 144)):
        assert main(["run", preset, "--out", "unused", "--list"]) == 0
        lines = capsys.readouterr().out.splitlines()
        assert len(lines) == cells
        for config in ("baseline", "lc", "cc", "optr", "optd", "opt", "lc+opt", "lc+cc+opt"):
            assert any(f", {config}, " in line for line in lines), (preset, config)
        assert any(line.endswith("repeat 3, arpz") for line in lines)
        assert "Rmax 100 Hz, depth 1000, optr, wifi-bad, repeat 1, arpz" in lines
        assert "Rmax 100 Hz, depth opt, optd, wifi-bad, repeat 1, arpz" in lines


def test_infeasible_optr_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = tmp_path / "s.toml"
    spec.write_text('name = "s"\nrmax_hz = [5]\ndepths = [1]\nconfigs = ["optr"]\n')
    assert main(["run", str(spec), "--out", str(tmp_path / "o"), "--list"]) == 2
    assert "no Opt(R) to run at" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_report_from_a_csv_file_into_another_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from arpz.experiment.results import append_row, error_row
    from arpz.experiment.spec import Cell

    csv = tmp_path / "committed" / "results.csv"
    csv.parent.mkdir()
    append_row(csv, error_row(Cell(100.0, 1, "lc", 1, "lan"), experiment="e", error="x", wall_s=1))
    out = tmp_path / "regenerated"
    assert main(["report", str(csv), "--out", str(out)]) == 0
    assert capsys.readouterr().out.splitlines() == [str(out / "REPORT.md")]
    assert "Cells that failed to run" in (out / "REPORT.md").read_text(encoding="utf-8")
