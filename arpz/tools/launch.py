"""Start a CEDDP and robots as real processes from config dicts: what the demo and the
experiment runner share.

Configs are written as real TOML files and loaded by ``python -m arpz.ceddp`` and
``python -m arpz.robot`` exactly as on a server and on robots, so every run also exercises the
user-facing entry points. Processes are stopped with SIGINT (the clean path) and killed only if
they do not stop in time, which is reported.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO, TypeVar

import tomli_w

from arpz.core.errors import ArpzError

T = TypeVar("T")


class LaunchError(ArpzError, RuntimeError):
    """A process did not start, stopped early, did not stop, or wrote no summary."""


class PortTaken(LaunchError):
    """The CEDDP could not listen on a port ``free_port`` had found free: another process
    took it in between (a port cannot be held for a child to bind). ``on_fresh_ports`` starts
    again on new ones; seen under parallel tests."""


#: how many times ``on_fresh_ports`` starts a fleet on fresh ports after ``PortTaken``
PORT_ATTEMPTS = 3
#: what Zenoh's log says when a listener's port is taken (TCP and UDP alike)
PORT_TAKEN_LOG = "Address already in use"


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A loopback port that was free a moment ago (bind to 0 and release): TCP, or UDP with
    ``socket.SOCK_DGRAM``. The one helper the tools, benchmarks and tests share."""
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class Proc:
    """A child process whose merged stdout/stderr is kept in memory and, unless spawned with
    ``log=False`` (the tests, where pytest shows it), in a log file."""

    name: str
    popen: subprocess.Popen[str]
    log_path: Path | None
    lines: list[str] = field(default_factory=list)
    _reader: threading.Thread | None = None

    @classmethod
    def spawn(
        cls,
        name: str,
        args: list[str],
        workdir: Path,
        *,
        log: bool = True,
        env: dict[str, str] | None = None,
    ) -> Proc:
        """Start ``python args...``; ``env`` adds to (or overrides) this process's environment."""
        popen = subprocess.Popen(
            [sys.executable, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=workdir,
            env=dict(os.environ, PYTHONUNBUFFERED="1", **(env or {})),
        )
        proc = cls(name, popen, workdir / f"{name}.log" if log else None)
        log_file = proc.log_path.open("w", encoding="utf-8") if proc.log_path else None

        def pump() -> None:
            assert popen.stdout is not None
            with popen.stdout, log_file or contextlib.nullcontext():
                for line in popen.stdout:
                    proc.lines.append(line)
                    if log_file is not None:
                        log_file.write(line)
                        log_file.flush()

        proc._reader = threading.Thread(target=pump, name=f"log-{name}", daemon=True)
        proc._reader.start()
        return proc

    def has_line(self, needle: str) -> bool:
        return any(needle in line for line in self.lines)

    def wait_line(self, needle: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.has_line(needle):
                return
            if self.popen.poll() is not None:
                break
            time.sleep(0.02)
        if self.has_line(needle):
            return
        raise LaunchError(
            f"{self.name} did not print {needle!r} within {timeout_s:g} s "
            f"(exit code {self.popen.poll()}); {self._where(tail=True)}"
        )

    def stop(self, timeout_s: float, *, sig: int = signal.SIGINT) -> int:
        """Send ``sig`` (SIGINT: the clean path) and wait; kill and raise if it does not stop."""
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
        try:
            return self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            # every thread's stack into the log (arpz.runtime.startup registers SIGUSR1), then kill
            self.popen.send_signal(signal.SIGUSR1)
            time.sleep(0.5)
            self.kill()
            raise LaunchError(
                f"{self.name} did not stop within {timeout_s:g} s of "
                f"{signal.Signals(sig).name} and was killed; {self._where(tail=False)}"
            ) from None

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait()
        if self._reader is not None:
            self._reader.join(timeout=10)

    def output(self) -> str:
        return "".join(self.lines)

    def tail(self, n: int = 15) -> str:
        return "".join(self.lines[-n:])

    def _where(self, *, tail: bool) -> str:
        """Where to read what it printed: its log (and its last lines), or all of it."""
        if self.log_path is None:
            return f"its output:\n{self.output()}"
        return f"see {self.log_path}" + (f":\n{self.tail()}" if tail else "")


def on_fresh_ports(start: Callable[[], T], say: Callable[[str], None]) -> T:
    """``start()``, again after ``PortTaken`` (up to ``PORT_ATTEMPTS`` times; ``say`` tells
    why): ``start`` must choose its ports on every call. Any other ``LaunchError``, and the
    last ``PortTaken``, go to the caller."""
    for attempt in range(1, PORT_ATTEMPTS + 1):
        try:
            return start()
        except PortTaken:
            if attempt == PORT_ATTEMPTS:
                raise
            say("a port was taken between its choice and the bind; starting again on new ports")
    raise AssertionError("unreachable")  # the loop returns or raises


@dataclass
class FleetSpec:
    """A CEDDP config and robot configs (dicts in the TOML schema of arpz.core.config)."""

    ceddp: dict[str, Any]
    robots: dict[str, dict[str, Any]]
    #: robots started (and waited for) before the others, e.g. the Hello relay
    first: tuple[str, ...] = ()


def run_fleet(
    spec: FleetSpec,
    workdir: Path,
    *,
    duration_s: float,
    until: Callable[[Proc], bool] | None = None,
    progress: TextIO | None = sys.stderr,
    label: str = "run",
) -> dict[str, Any]:
    """Start the CEDDP then the robots, run for ``duration_s`` (or until ``until(ceddp)``), stop
    robots then CEDDP with SIGINT, and return the CEDDP's summary.json. Raises LaunchError with
    every problem found (a process that exited early, non-zero, did not stop, no summary)."""
    workdir.mkdir(parents=True, exist_ok=True)
    ceddp_conf = dict(spec.ceddp, summary_json=str(workdir / "summary.json"))
    ceddp_path = workdir / "ceddp.toml"
    ceddp_path.write_text(tomli_w.dumps(ceddp_conf), encoding="utf-8")
    robot_paths = {}
    for robot, conf in spec.robots.items():
        path = workdir / f"{robot}.toml"
        path.write_text(tomli_w.dumps(conf), encoding="utf-8")
        robot_paths[robot] = path
    procs: list[Proc] = []
    try:
        ceddp = Proc.spawn("ceddp", ["-m", "arpz.ceddp", "--config", str(ceddp_path)], workdir)
        procs.append(ceddp)
        try:
            ceddp.wait_line("ready on", timeout_s=60)
        except LaunchError as exc:
            if ceddp.popen.poll() is not None and ceddp.has_line(PORT_TAKEN_LOG):
                raise PortTaken(str(exc)) from None
            raise
        order = [r for r in spec.first if r in robot_paths]
        order += [r for r in robot_paths if r not in order]
        robots: list[Proc] = []
        for group in (
            [r for r in order if r in spec.first],
            [r for r in order if r not in spec.first],
        ):
            started = [
                Proc.spawn(r, ["-m", "arpz.robot", "--config", str(robot_paths[r])], workdir)
                for r in group
            ]
            procs.extend(started)
            robots.extend(started)
            for proc in started:
                proc.wait_line("running", timeout_s=60)
        if progress is not None:
            print(
                f"{label}: CEDDP on {','.join(spec.ceddp.get('listen', []))} "
                f"(fleet {spec.ceddp.get('fleet', 'default')!r}) and {len(robots)} robots "
                f"running; logs in {workdir}",
                file=progress,
            )
        # a progress line rewritten in place is for a person at a terminal; in a log file it
        # would be hundreds of lines of "\r"
        live = progress is not None and progress.isatty()
        start = time.monotonic()
        while (elapsed := time.monotonic() - start) < duration_s:
            for proc in procs:
                if proc.popen.poll() is not None:
                    raise LaunchError(
                        f"{proc.name} exited early with code {proc.popen.returncode}; "
                        f"see {proc.log_path}:\n{proc.tail()}"
                    )
            if until is not None and until(ceddp):
                break
            if live and progress is not None:
                print(
                    f"\r{label}: {elapsed:5.1f}/{duration_s:.0f} s",
                    end="",
                    file=progress,
                    flush=True,
                )
            time.sleep(min(0.25, max(duration_s - elapsed, 0.0)))
        if progress is not None:
            print(
                f"{chr(13) if live else ''}{label}: {time.monotonic() - start:5.1f} s, stopping",
                file=progress,
            )
        failures = []
        # in reverse start order: robots started first (e.g. a Hello relay) stop last
        for proc in reversed(robots):
            try:
                code = proc.stop(timeout_s=20)
            except LaunchError as exc:
                failures.append(str(exc))
                continue
            if code != 0:
                failures.append(f"{proc.name} exited with code {code}; see {proc.log_path}")
        code = ceddp.stop(timeout_s=30)
        if code != 0:
            failures.append(f"ceddp exited with code {code}; see {ceddp.log_path}")
        summary_path = workdir / "summary.json"
        if not summary_path.exists():
            failures.append(f"the CEDDP wrote no summary ({summary_path})")
        if failures:
            raise LaunchError("; ".join(failures))
        summary: dict[str, Any] = json.loads(summary_path.read_text(encoding="utf-8"))
        return summary
    finally:
        for proc in procs:
            proc.kill()
