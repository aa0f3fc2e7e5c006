"""Start a CEDDP and robots as real processes from config dicts: what the demo and the
experiment runner share.

Configs are written as real TOML files and loaded by ``python -m arpz.ceddp`` and
``python -m arpz.robot`` exactly as on a server and on robots, so every run also exercises the
user-facing entry points. Processes are stopped with SIGINT (the clean path) and killed only if
they do not stop in time, which is reported.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO


class LaunchError(RuntimeError):
    """A process did not start, stopped early, did not stop, or wrote no summary."""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, Sequence):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def toml_dumps(data: Mapping[str, Any], prefix: str = "") -> str:
    """TOML for nested dicts of scalars and lists (tables after the plain keys)."""
    plain = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, Mapping)]
    text = "\n".join(plain) + ("\n" if plain else "")
    for key, value in data.items():
        if isinstance(value, Mapping):
            name = f"{prefix}{key}"
            text += f"\n[{name}]\n" + toml_dumps(value, prefix=f"{name}.")
    return text


@dataclass
class Proc:
    """A child process whose merged stdout/stderr is kept in memory and in a log file."""

    name: str
    popen: subprocess.Popen[str]
    log_path: Path
    lines: list[str] = field(default_factory=list)
    _reader: threading.Thread | None = None

    @classmethod
    def spawn(cls, name: str, args: list[str], workdir: Path) -> Proc:
        popen = subprocess.Popen(
            [sys.executable, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=workdir,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        proc = cls(name, popen, workdir / f"{name}.log")
        log = proc.log_path.open("w", encoding="utf-8")

        def pump() -> None:
            assert popen.stdout is not None
            with popen.stdout, log:
                for line in popen.stdout:
                    proc.lines.append(line)
                    log.write(line)
                    log.flush()

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
            f"{self.name} did not print {needle!r} within {timeout_s:.0f} s "
            f"(exit code {self.popen.poll()}); see {self.log_path}:\n{self.tail()}"
        )

    def stop(self, timeout_s: float) -> int:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGINT)
        try:
            return self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            # every thread's stack into the log (arpz.cli registers SIGUSR1), then kill
            self.popen.send_signal(signal.SIGUSR1)
            time.sleep(0.5)
            self.kill()
            raise LaunchError(
                f"{self.name} did not stop within {timeout_s:.0f} s of SIGINT and was killed; "
                f"see {self.log_path}"
            ) from None

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait()
        if self._reader is not None:
            self._reader.join(timeout=10)

    def tail(self, n: int = 15) -> str:
        return "".join(self.lines[-n:])


@dataclass
class FleetSpec:
    """A CEDDP config and robot configs (dicts in the TOML schema of arpz.config)."""

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
    ceddp_path.write_text(toml_dumps(ceddp_conf), encoding="utf-8")
    robot_paths = {}
    for robot, conf in spec.robots.items():
        path = workdir / f"{robot}.toml"
        path.write_text(toml_dumps(conf), encoding="utf-8")
        robot_paths[robot] = path
    procs: list[Proc] = []
    try:
        ceddp = Proc.spawn("ceddp", ["-m", "arpz.ceddp", "--config", str(ceddp_path)], workdir)
        procs.append(ceddp)
        ceddp.wait_line("ready on", timeout_s=60)
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
                f"{label}: CEDDP and {len(robots)} robots running; logs in {workdir}", file=progress
            )
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
            if progress is not None:
                print(
                    f"\r{label}: {elapsed:5.1f}/{duration_s:.0f} s",
                    end="",
                    file=progress,
                    flush=True,
                )
            time.sleep(min(0.25, max(duration_s - elapsed, 0.0)))
        if progress is not None:
            print(f"\r{label}: {time.monotonic() - start:5.1f} s, stopping", file=progress)
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
