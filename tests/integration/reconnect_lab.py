"""A small network lab in Linux namespaces for the reconnection tests (issue 39).

Two namespaces joined by two access points::

    robot ns                      server ns
    r0 10.77.1.2/24 ── veth ── r0p ─ br1 10.77.1.1/24     CEDDP on 10.77.0.1 (lo)
       (roams to 10.77.2.2/24)       br2 10.77.2.1/24

The CEDDP listens on an address of the server's loopback, reachable through either access point,
so that it always answers from the address the robot dialled (a UDP server answering from another
of its addresses breaks a connected UDP client). ``dead_zone`` drops everything on both ends with
nftables ``netdev`` ingress rules (silent to the sender, as a radio out of range: no ICMP, no
carrier loss); ``roam`` moves the robot's veth to the other bridge and changes its address and
default route, as a robot that joins another access point's subnet does.

Names are ``arpzrc-<pid>-<n>-{s,r}``, unique per test and per process; ``Lab.close`` ends every
process it started (by pid) and deletes both namespaces (their interfaces go with them), on every
exit path. Namespaces left by a process that no longer exists (a test run killed with -9) are
deleted by the next ``Lab`` of this helper.

Needs root, ``ip`` and ``nft``: ``lab_missing()`` says why it cannot run, for a skip.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

PREFIX = "arpzrc-"
CEDDP_ADDRESS = "10.77.0.1"
AP = {1: "10.77.1.1", 2: "10.77.2.1"}
ROBOT = {1: "10.77.1.2", 2: "10.77.2.2"}
_counter = itertools.count(1)


def lab_missing() -> str | None:
    """Why the lab cannot run here (None: it can)."""
    if os.geteuid() != 0:
        return "needs root (network namespaces)"
    for tool in ("ip", "nft"):
        if shutil.which(tool) is None:
            return f"needs the '{tool}' command (apt-get install iproute2 nftables)"
    return None


def _run(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(list(args), capture_output=True, text=True, timeout=20)
    if check and done.returncode != 0:
        raise RuntimeError(f"{' '.join(args)}: {done.stderr.strip() or done.stdout.strip()}")
    return done


def _remove_stale() -> None:
    """Delete ``arpzrc-<pid>-...`` namespaces whose process is gone (a killed test run)."""
    listed = _run("ip", "netns", "list", check=False).stdout.split()
    for name in listed:
        if not name.startswith(PREFIX):
            continue
        pid = name[len(PREFIX) :].split("-", 1)[0]
        if pid.isdigit() and not Path(f"/proc/{pid}").exists():
            _run("ip", "netns", "del", name, check=False)


class Lab:
    """The two namespaces; a context manager (``with Lab() as lab:``)."""

    def __init__(self) -> None:
        base = f"{PREFIX}{os.getpid()}-{next(_counter)}"
        self.server_ns = f"{base}-s"
        self.robot_ns = f"{base}-r"
        self.ap = 1
        self.dead = False
        self._procs: list[subprocess.Popen[str]] = []
        self._created: list[str] = []

    # -- set-up and tear-down -------------------------------------------------------------

    def __enter__(self) -> Lab:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        _remove_stale()
        s, r = self.server_ns, self.robot_ns
        for ns in (s, r):
            _run("ip", "netns", "add", ns)
            self._created.append(ns)
            _run("ip", "-n", ns, "link", "set", "lo", "up")
        _run("ip", "-n", s, "addr", "add", f"{CEDDP_ADDRESS}/32", "dev", "lo")
        for ap, address in AP.items():
            _run("ip", "-n", s, "link", "add", f"br{ap}", "type", "bridge")
            _run("ip", "-n", s, "addr", "add", f"{address}/24", "dev", f"br{ap}")
            _run("ip", "-n", s, "link", "set", f"br{ap}", "up")
        # made inside the robot's namespace: no name is ever taken in the host's
        _run("ip", "-n", r, "link", "add", "r0", "type", "veth", "peer", "name", "r0p", "netns", s)
        _run("ip", "-n", s, "link", "set", "r0p", "master", "br1", "up")
        _run("ip", "-n", r, "addr", "add", f"{ROBOT[1]}/24", "dev", "r0")
        _run("ip", "-n", r, "link", "set", "r0", "up")
        _run("ip", "-n", r, "route", "add", "default", "via", AP[1])
        for ns, dev in ((s, "r0p"), (r, "r0")):
            _run("ip", "netns", "exec", ns, "nft", "add", "table", "netdev", "arpzrc")
            _run(
                "ip", "netns", "exec", ns, "nft", "add", "chain", "netdev", "arpzrc", "ingress",
                f"{{ type filter hook ingress device {dev} priority 0 ; policy accept ; }}",
            )  # fmt: skip
        # the bridge port forwards at once (no STP learning delay)
        _run("ip", "-n", s, "link", "set", "br1", "type", "bridge", "forward_delay", "0")
        _run("ip", "-n", s, "link", "set", "br2", "type", "bridge", "forward_delay", "0")
        deadline = time.monotonic() + 10
        while not self.reachable():
            if time.monotonic() > deadline:
                raise RuntimeError("the lab's robot cannot reach the CEDDP's address")
            time.sleep(0.05)

    def reachable(self) -> bool:
        """A TCP connection from the robot to a closed port of the CEDDP's address is refused
        (there is no ping here): the route, ARP and bridge all work."""
        probe = (
            "import socket,sys\n"
            "s=socket.socket(); s.settimeout(1)\n"
            "try: s.connect((sys.argv[1], 9))\n"
            "except ConnectionRefusedError: sys.exit(0)\n"
            "except OSError: sys.exit(1)\n"
        )
        done = _run(
            "ip", "netns", "exec", self.robot_ns, sys.executable, "-c", probe, CEDDP_ADDRESS,
            check=False,
        )  # fmt: skip
        return done.returncode == 0

    def close(self) -> None:
        """End every process started here (by pid), then delete the namespaces."""
        for proc in self._procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGKILL)
        for proc in self._procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(10)
        for ns in reversed(self._created):
            _run("ip", "netns", "del", ns, check=False)
        self._created.clear()

    # -- faults -------------------------------------------------------------------------

    def dead_zone(self, on: bool) -> float:
        """Drop everything both ways (on) or nothing (off); returns when it took effect
        (``time.time()``, the clock the processes' logs can be compared with)."""
        for ns in (self.server_ns, self.robot_ns):
            if on:
                _run("ip", "netns", "exec", ns, "nft", "add", "rule", "netdev", "arpzrc",
                     "ingress", "drop")  # fmt: skip
            else:
                _run("ip", "netns", "exec", ns, "nft", "flush", "chain", "netdev", "arpzrc",
                     "ingress")  # fmt: skip
        self.dead = on
        return time.time()

    def roam(self) -> float:
        """Move the robot to the other access point: another subnet, another address, another
        default route. Returns when its new address is usable (``time.time()``)."""
        old, new = self.ap, 3 - self.ap
        s, r = self.server_ns, self.robot_ns
        _run("ip", "-n", s, "link", "set", "r0p", "master", f"br{new}")
        _run("ip", "-n", r, "addr", "del", f"{ROBOT[old]}/24", "dev", "r0")
        _run("ip", "-n", r, "addr", "add", f"{ROBOT[new]}/24", "dev", "r0")
        _run("ip", "-n", r, "route", "replace", "default", "via", AP[new])
        self.ap = new
        return time.time()

    # -- processes ------------------------------------------------------------------------

    def popen(
        self, ns: str, args: list[str], *, cwd: Path, log: Path, env: dict[str, str] | None = None
    ) -> subprocess.Popen[str]:
        """``python ARGS`` in namespace ``ns`` (``ip netns exec`` execs it: same pid), its output
        into ``log``."""
        out = log.open("w")
        proc = subprocess.Popen(
            ["ip", "netns", "exec", ns, sys.executable, *args],
            cwd=cwd,
            stdout=out,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        )
        out.close()
        self._procs.append(proc)
        return proc


def make_certs(out: Path, robots: list[str], fleet: str) -> Path:
    """The deploy script's certificates for a CEDDP at the lab's address."""
    script = Path(__file__).resolve().parents[2] / "deploy" / "tls" / "make_fleet_certs.py"
    args = [sys.executable, str(script), "--out", str(out), "--fleet", fleet]
    args += ["--server-ip", CEDDP_ADDRESS, *robots]
    done = subprocess.run(args, capture_output=True, text=True, timeout=60)
    if done.returncode != 0:
        raise RuntimeError(done.stdout + done.stderr)
    return out
