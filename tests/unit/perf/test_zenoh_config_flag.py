"""``--zenoh-config FILE`` on every ``python -m arpz.perf`` command: carried into the session's
settings (loaded first, arpz's own settings on top) and checked before any session opens."""

from __future__ import annotations

from pathlib import Path

import pytest

from arpz.perf.__main__ import _settings, build_parser, main

COMMANDS = {
    "router": ["router", "--listen", "tcp/127.0.0.1:1"],
    "pub": ["pub", "--connect", "tcp/127.0.0.1:1", "--count", "1"],
    "sub": ["sub", "--connect", "tcp/127.0.0.1:1"],
    "ping": ["ping", "--connect", "tcp/127.0.0.1:1", "--count", "1"],
    "pong": ["pong", "--connect", "tcp/127.0.0.1:1"],
    "fleet": ["fleet"],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_takes_the_flag(command: str, tmp_path: Path) -> None:
    path = tmp_path / "z.json5"
    args = build_parser().parse_args([*COMMANDS[command], "--zenoh-config", str(path)])
    assert args.zenoh_config == str(path)
    settings = _settings(args, mode="client", connect=["tcp/127.0.0.1:1"])
    assert settings.config_file == str(path)
    assert list(settings.connect) == ["tcp/127.0.0.1:1"]  # arpz's settings stay on top


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_config_that_does_not_parse_is_refused_with_exit_2(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.json5"
    path.write_text("{ transport: { shared_memory: ")
    assert main([*COMMANDS[command], "--zenoh-config", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"arpz perf {command}: error:" in err and "bad.json5" in err
