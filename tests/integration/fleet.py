"""Start and stop real CEDDP and robot processes for the integration tests."""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from arpz.netem import Impairments, NetemProxy
from arpz.tools.launch import PORT_TAKEN_LOG, LaunchError, PortTaken, Proc, on_fresh_ports
from tests.support import free_port, free_udp_port

#: The environment of a process whose resident memory a test judges (soak, abuse). glibc's
#: malloc otherwise caches freed memory in per-thread arenas and raises its mmap threshold after
#: the first large free, so the same workload can leave RSS one step of tens of MB higher at a
#: random round and keep it (seen in CI: +38 MB once at round 14 of 20, then flat). With a fixed
#: threshold large buffers are returned to the kernel when freed and with two arenas the caches
#: stay small, so RSS follows what the program keeps: a leak still shows, the allocator's moods
#: do not.
STEADY_MALLOC = {"MALLOC_ARENA_MAX": "2", "MALLOC_MMAP_THRESHOLD_": "131072"}


class Process:
    """A ``python -m arpz...`` child for the tests: arpz.tools.launch's Proc, without a log file
    (a failure's message carries the whole output instead)."""

    def __init__(
        self, name: str, args: list[str], cwd: Path, env: dict[str, str] | None = None
    ) -> None:
        self.name = name
        self._proc = Proc.spawn(name, args, cwd, log=False, env=env)

    @property
    def popen(self) -> subprocess.Popen[str]:
        return self._proc.popen

    @property
    def lines(self) -> list[str]:
        return self._proc.lines

    def output(self) -> str:
        return self._proc.output()

    def has_line(self, needle: str) -> bool:
        return self._proc.has_line(needle)

    def wait_for(self, needle: str, timeout_s: float = 30) -> None:
        self._proc.wait_line(needle, timeout_s)

    def interrupt(self, timeout_s: float = 20, sig: int = signal.SIGINT) -> int:
        """Stop with ``sig`` and return the exit code; raises LaunchError (after a stack dump and
        a kill) if it does not stop within ``timeout_s``. The output is complete on return."""
        try:
            return self._proc.stop(timeout_s, sig=sig)
        finally:
            self._proc.kill()

    def kill(self) -> None:
        self._proc.kill()


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
    top: str = "",
) -> Path:
    """``top``: top-level keys (before any table); ``extra``: tables, appended at the end."""
    path = tmp / f"{robot}.toml"
    text = (
        f'robot_id = "{robot}"\nfleet = "{fleet}"\nconnect = ["{endpoint}"]\n'
        f'preset = "{preset}"\npreset_rate_hz = {rate_hz}\nstats_period_s = 0.2\n{top}'
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
    env: dict[str, str] | None = None,
) -> Iterator[tuple[Process, str]]:
    """A CEDDP on a fresh port; started again on a new one if another process took it between
    ``free_port`` and the bind (``arpz.tools.launch.on_fresh_ports``' rule: a CI run failed on that
    race)."""

    def start() -> tuple[Process, str]:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        listen = ", ".join(f'"{e}"' for e in (endpoint, *also_listen))
        config = tmp / "ceddp.toml"
        config.write_text(
            f'fleet = "{fleet}"\nlisten = [{listen}]\nrrd = "{(tmp / "ceddp.rrd").as_posix()}"\n'
            f'summary_json = "{(tmp / "summary.json").as_posix()}"\nmetrics_period_s = 0.2\n'
            f"{extra}" + (f'[hello]\nrelay = "{relay}"\n' if relay else "")
        )
        proc = Process("ceddp", ["-m", "arpz.ceddp", "--config", str(config)], tmp, env)
        try:
            proc.wait_for("ready on")
        except LaunchError as exc:
            proc.kill()
            if PORT_TAKEN_LOG in proc.output():
                raise PortTaken(str(exc)) from None
            raise
        return proc, endpoint

    proc, endpoint = on_fresh_ports(start, lambda why: print(f"ceddp: {why}", flush=True))
    try:
        yield proc, endpoint
    finally:
        proc.kill()


@contextmanager
def robots(
    tmp: Path, configs: list[Path], env: dict[str, str] | None = None
) -> Iterator[list[Process]]:
    procs = [
        Process(path.stem, ["-m", "arpz.robot", "--config", str(path)], tmp, env)
        for path in configs
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


@dataclasses.dataclass
class UdpLink:
    """An emulated radio: a UDP endpoint for the CEDDP to listen on, and a clean ``arpz.netem``
    proxy in front of it that a robot connects to (start it, then ``impair`` it once the Zenoh
    session is up: a lost handshake is not what a test is about)."""

    ceddp_endpoint: str
    robot_endpoint: str
    proxy: NetemProxy

    def impair(self, impairments: Impairments) -> None:
        """Both directions impaired from now on (the time so far counts as clean)."""
        now = dataclasses.replace(impairments, clean_s=self.proxy.elapsed_s)
        self.proxy.set_impairments(now, now)


def udp_link() -> UdpLink:
    ceddp_endpoint = f"udp/127.0.0.1:{free_udp_port()}"
    robot_endpoint = f"udp/127.0.0.1:{free_udp_port()}"
    return UdpLink(
        ceddp_endpoint, robot_endpoint, NetemProxy(robot_endpoint, ceddp_endpoint, Impairments())
    )
