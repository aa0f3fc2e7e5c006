"""The one entry point, as a new user meets it: every command listed on stdout, ``--version``
everywhere, an unknown command refused with exit 2 (issue 18, "The command line")."""

from __future__ import annotations

import subprocess
import sys

import pytest

from arpz.__main__ import COMMANDS, main


def test_the_entry_point_lists_every_command_on_stdout(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    out, err = capsys.readouterr()
    for name in ("robot", "ceddp", "topic", "record", "play", "doctor", "perf", "netem"):
        assert f"\n  {name} " in out, name
    for name in ("experiment", "configure", "demo"):
        assert f"\n  {name} " in out, name
    assert err == ""


def test_an_unknown_command_is_an_error_with_the_list(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["recrod"]) == 2
    _, err = capsys.readouterr()
    assert "arpz: error: unknown command 'recrod'" in err and "did you mean record" in err


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_answers_version(name: str) -> None:
    """Through a real interpreter, so that each command's module really imports and parses."""
    proc = subprocess.run(
        [sys.executable, "-m", "arpz", name, "--version"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("arpz ") and "eclipse-zenoh 1." in proc.stdout


def test_the_top_level_version(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--version"]) == 0
    assert "eclipse-zenoh" in capsys.readouterr().out
