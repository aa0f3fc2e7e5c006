"""Start a CEDDP and robots with mutual TLS (or TLS + user/password) and access control; measure
what real processes use.

The certificates and the Zenoh JSON5 files come from ``deploy/tls/make_fleet_certs.py`` run with
real openssl into the test's temporary folder, so the tests exercise exactly what an operator
deploys; only the endpoints differ (free loopback ports, applied on top of the JSON5 by the arpz
TOML as in production).
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from arpz.core.transport import SessionSettings
from arpz.transport.zenoh import ZenohTransport
from tests.integration.fleet import Process, write_robot
from tests.support import free_port

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "deploy" / "tls" / "make_fleet_certs.py"


def make_fleet_tls(
    out: Path,
    fleet: str,
    robots: list[str],
    *,
    observers: tuple[str, ...] = (),
    operators: tuple[str, ...] = (),
    usrpwd: bool = False,
) -> Path:
    """Run the deploy script: a CA, a server certificate for 127.0.0.1, one per client."""
    args = [sys.executable, str(SCRIPT), "--out", str(out), "--fleet", fleet]
    args += ["--server-ip", "127.0.0.1", "--server-name", "localhost"]
    for observer in observers:
        args += ["--observer", observer]
    for operator in operators:
        args += ["--operator", operator]
    if usrpwd:
        args.append("--usrpwd")
    done = subprocess.run([*args, *robots], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    return out


def client_config(tls: Path, name: str, variant: str = "") -> Path:
    """``variant`` is "" (mutual TLS) or "-usrpwd"."""
    return tls / "zenoh" / f"{name}-client{variant}.json5"


@contextmanager
def secure_ceddp(
    tmp: Path, tls: Path, *, fleet: str, variant: str = "", extra: str = ""
) -> Iterator[tuple[Process, str]]:
    endpoint = f"tls/127.0.0.1:{free_port()}"
    config = tmp / "ceddp.toml"
    config.write_text(
        f'fleet = "{fleet}"\nlisten = ["{endpoint}"]\n'
        f'zenoh_config = "{(tls / "zenoh" / f"ceddp-router{variant}.json5").as_posix()}"\n'
        f'rrd = "{(tmp / "ceddp.rrd").as_posix()}"\n'
        f'summary_json = "{(tmp / "summary.json").as_posix()}"\nmetrics_period_s = 0.2\n{extra}'
    )
    proc = Process("ceddp", ["-m", "arpz.ceddp", "--config", str(config)], tmp)
    try:
        proc.wait_for("ready on")
        yield proc, endpoint
    finally:
        proc.kill()


def write_secure_robot(
    tmp: Path,
    robot: str,
    endpoint: str,
    zenoh_config: Path,
    *,
    fleet: str,
    preset: str,
    rate_hz: float = 50,
    hello: bool = False,
    extra: str = "",
) -> Path:
    """fleet.write_robot's file, plus the Zenoh JSON5 with this robot's certificate or password;
    ``extra`` (TOML tables) goes at the end."""
    path = write_robot(
        tmp, robot, endpoint, preset=preset, rate_hz=rate_hz, hello=hello, fleet=fleet
    )
    path.write_text(
        f'zenoh_config = "{zenoh_config.as_posix()}"\nconnect_timeout_s = 10\n'
        + path.read_text()
        + extra
    )
    return path


def open_client(endpoint: str, config_file: Path | None, *, timeout_s: float = 5) -> ZenohTransport:
    """A raw Zenoh client session (the caller closes it); ``config_file`` None = no TLS files."""
    return ZenohTransport.open(
        SessionSettings(
            mode="client",
            connect=[endpoint],
            config_file=str(config_file) if config_file is not None else None,
        ),
        timeout_s=timeout_s,
    )


def rss_mb(pid: int) -> float:
    """Resident memory of a process from /proc (Linux), in MiB: what the soak and abuse tests
    watch for growth."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for process {pid}")
