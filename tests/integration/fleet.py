"""Start and stop real CEDDP and robot processes for the integration tests."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from tests.support import free_port, wait_until


class Process:
    def __init__(self, name: str, args: list[str], cwd: Path) -> None:
        self.name = name
        self.lines: list[str] = []
        self.popen = subprocess.Popen(
            [sys.executable, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=cwd,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()

    def _pump(self) -> None:
        assert self.popen.stdout is not None
        with self.popen.stdout:
            for line in self.popen.stdout:
                self.lines.append(line)

    def _reap(self) -> None:
        self._reader.join(timeout=10)

    def output(self) -> str:
        return "".join(self.lines)

    def wait_for(self, needle: str, timeout_s: float = 30) -> None:
        try:
            wait_until(
                lambda: needle in self.output() or self.popen.poll() is not None,
                timeout_s=timeout_s,
                what=f"{self.name} to print {needle!r}",
            )
        finally:
            pass
        assert needle in self.output(), f"{self.name} exited early:\n{self.output()}"

    def interrupt(self, timeout_s: float = 20, sig: int = signal.SIGINT) -> int:
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
        try:
            code = self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            # every thread's stack into the output (arpz.cli registers SIGUSR1), then fail
            self.popen.send_signal(signal.SIGUSR1)
            time.sleep(0.5)
            self.kill()
            raise AssertionError(
                f"{self.name} did not stop within {timeout_s} s of {sig!r}:\n{self.output()}"
            ) from None
        finally:
            self.kill()
        return code

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait(timeout=10)
        self._reap()


def write_robot(
    tmp: Path,
    robot: str,
    endpoint: str,
    *,
    preset: str,
    rate_hz: float = 50,
    hello: bool = False,
    fleet: str = "itest",
    extra: str = "",
) -> Path:
    path = tmp / f"{robot}.toml"
    text = (
        f'robot_id = "{robot}"\nfleet = "{fleet}"\nconnect = ["{endpoint}"]\n'
        f'preset = "{preset}"\npreset_rate_hz = {rate_hz}\nstats_period_s = 0.2\n'
        f"[local_cache]\nmax_silence_s = 0.5\n"
    )
    if hello:
        text += "[hello]\nenabled = true\nrate_hz = 20\n"
    text += extra
    path.write_text(text)
    return path


@contextmanager
def ceddp(
    tmp: Path,
    *,
    fleet: str = "itest",
    relay: str | None = None,
    extra: str = "",
    also_listen: tuple[str, ...] = (),
) -> Iterator[tuple[Process, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    listen = ", ".join(f'"{e}"' for e in (endpoint, *also_listen))
    config = tmp / "ceddp.toml"
    config.write_text(
        f'fleet = "{fleet}"\nlisten = [{listen}]\nrrd = "{(tmp / "ceddp.rrd").as_posix()}"\n'
        f'summary_json = "{(tmp / "summary.json").as_posix()}"\nmetrics_period_s = 0.2\n{extra}'
        + (f'[hello]\nrelay = "{relay}"\n' if relay else "")
    )
    proc = Process("ceddp", ["-m", "arpz.ceddp", "--config", str(config)], tmp)
    try:
        proc.wait_for("ready on")
        yield proc, endpoint
    finally:
        proc.kill()


@contextmanager
def robots(tmp: Path, configs: list[Path]) -> Iterator[list[Process]]:
    procs = [
        Process(path.stem, ["-m", "arpz.robot", "--config", str(path)], tmp) for path in configs
    ]
    try:
        for proc in procs:
            proc.wait_for("running")
        yield procs
    finally:
        for proc in procs:
            proc.kill()


def settle(seconds: float) -> None:
    """Let a fleet run for a while (the one place a fixed wait is the point of the test)."""
    time.sleep(seconds)
