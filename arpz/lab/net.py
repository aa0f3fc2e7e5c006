"""The kernel lab's network: namespaces, veth pairs and access point bridges, and the changes the
profiles make to them (loss, dead zones, bandwidth, roaming).

```
 robot1 ns            access point ns (router, ip_forward)              ceddp ns
 azl<id>r1 ──veth── azl<id>r1a ┐
                               ├─ bridge azl<id>b0  10.77.1.1/24 ┐
 robot2 ns                     │                                 ├── azl<id>ca ──veth── azl<id>c
 azl<id>r2 ──veth── azl<id>r2a ┘                                 │   10.77.0.1         10.77.0.2
                                  bridge azl<id>b1  10.77.2.1/24 ┘ (roaming: a robot's port
 robots 10.77.1.(10+N)/24, default via 10.77.1.1 src itself          moves here, its address
                                                                       becomes 10.77.2.(10+N))
```

Nothing of the lab is in the host's own namespace: every link is created inside the access
point's namespace with its peer placed straight into the robot's (or the CEDDP's), so deleting
the namespaces deletes everything, and two labs (two test workers) never see each other.

**Why pyroute2.** The lab talks netlink directly through pyroute2 (namespaces, links, bridges,
addresses, routes, the tbf qdisc): each change is a call with typed arguments that raises an
error carrying the kernel's errno, instead of an ``ip``/``tc`` command line to build, run in a
namespace and parse back, at one process per change. nftables is the exception: ``nft -f -``
applies a whole ruleset text as one atomic transaction (pyroute2's nftables support is partial),
so the loss rules are text (``arpz.lab.nft``). Processes run in a namespace through
``ip netns exec``, which execs in place: the pid a caller holds is the process's own.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

from arpz.lab import nft
from arpz.lab.names import (
    AP_SERVER_ADDRESS,
    CEDDP_ADDRESS,
    NFT_TABLE,
    PREFIXLEN,
    LabError,
    LabInterrupted,
    LabNames,
    LabUnavailable,
    check_robot_names,
    gateway,
    new_lab_id,
    robot_address,
)
from arpz.lab.profiles import CLEAN, LinkState
from arpz.lab.timeline import Timeline
from arpz.tools.launch import Proc

try:
    from pyroute2 import IPRoute, netns
except ImportError:  # a robot install: no server extra, no lab
    IPRoute = netns = None

#: who owns which lab: ``<id>.json`` with the owner's pid and start time (``lab clean`` leaves
#: the labs of live owners alone)
RUN_DIR = Path("/run/arpz-lab")
#: tbf's queue: what waits longer behind the rate limit is dropped (as a radio's queue would)
TBF_LATENCY = "50ms"
#: the netlink protocol of routing (links, addresses, routes, qdiscs)
NETLINK_ROUTE = 0
#: seconds a command in a namespace may take
COMMAND_TIMEOUT_S = 30.0

# Proc.spawn runs ``python ARGS``: ARGS run this, which becomes ``ip netns exec NS python ...``
# by exec (same pid), so the caller's pid is the real process's.
_IN_NETNS = (
    "import os, sys; os.execv(sys.argv[1], "
    "[sys.argv[1], 'netns', 'exec', sys.argv[2], sys.executable, *sys.argv[3:]])"
)


# ------------------------------------------------------------------------------ availability


def _which(name: str) -> str | None:
    """A system tool, also where a non-root PATH does not look (/usr/sbin, /sbin)."""
    return shutil.which(name) or next(
        (f"{d}/{name}" for d in ("/usr/sbin", "/sbin") if os.access(f"{d}/{name}", os.X_OK)),
        None,
    )


def _effective_capabilities() -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("CapEff:"):
                return int(line.split()[1], 16)
    except OSError:
        pass
    return 0


CAP_NET_ADMIN = 12
CAP_SYS_ADMIN = 21


def missing() -> list[str]:
    """What this machine lacks for the lab (empty: nothing)."""
    if not sys.platform.startswith("linux"):
        return ["Linux (network namespaces)"]
    problems = []
    if IPRoute is None:
        problems.append("pyroute2 (pip install 'arpz[server]')")
    for tool, package in (("ip", "iproute2"), ("nft", "nftables")):
        if _which(tool) is None:
            problems.append(f"the `{tool}` command (apt-get install {package})")
    caps = _effective_capabilities()
    for bit, name in ((CAP_NET_ADMIN, "CAP_NET_ADMIN"), (CAP_SYS_ADMIN, "CAP_SYS_ADMIN")):
        if not caps >> bit & 1:
            problems.append(f"{name} (run as root)")
    return problems


def check_available() -> None:
    """Raise LabUnavailable naming everything missing."""
    problems = missing()
    if problems:
        raise LabUnavailable("the kernel lab needs " + "; ".join(problems))


def tool(name: str) -> str:
    path = _which(name)
    if path is None:
        raise LabUnavailable(f"the kernel lab needs the `{name}` command")
    return path


T = TypeVar("T")


def in_namespace(namespace: str, work: Callable[[], T]) -> T:
    """``work()`` on a short-lived thread that entered ``namespace`` (``setns`` moves the
    calling thread only): sockets it opens live in that namespace and stay there, whichever
    thread uses them later. Cheaper than pyroute2's own ``netns=`` (a forked child per socket)."""
    assert netns is not None
    result: list[T] = []
    failure: list[BaseException] = []

    def enter_and_work() -> None:
        try:
            netns.setns(namespace, flags=0, fork=False)
            result.append(work())
        except BaseException as exc:
            failure.append(exc)

    thread = threading.Thread(target=enter_and_work, name=f"netns-{namespace}")
    thread.start()
    thread.join()
    if failure:
        raise failure[0]
    return result[0]


@contextlib.contextmanager
def netlink(namespace: str) -> Iterator[Any]:
    """pyroute2's ``IPRoute`` on a netlink socket of ``namespace``."""
    assert IPRoute is not None
    sock = in_namespace(
        namespace,
        lambda: socket.socket(socket.AF_NETLINK, socket.SOCK_DGRAM, NETLINK_ROUTE),
    )
    with sock, IPRoute(use_socket=sock) as ipr:
        yield ipr


# ------------------------------------------------------------------------------ owners


def _start_time(pid: int) -> str | None:
    """The process's start time (field 22 of /proc/PID/stat): a pid reused later differs."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rpartition(")")[2].split()[19]


def write_owner(lab_id: str) -> Path:
    RUN_DIR.mkdir(parents=True, exist_ok=True)
    path = RUN_DIR / f"{lab_id}.json"
    pid = os.getpid()
    path.write_text(json.dumps({"pid": pid, "start": _start_time(pid)}), encoding="utf-8")
    return path


def owner_alive(lab_id: str) -> bool:
    """Whether the process that built lab ``lab_id`` still runs."""
    try:
        owner = json.loads((RUN_DIR / f"{lab_id}.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return owner.get("start") is not None and _start_time(int(owner["pid"])) == owner["start"]


def kill_pids_in(namespaces: Sequence[str]) -> list[int]:
    """Kill (by pid) every process still inside ``namespaces``; the pids killed."""
    assert netns is not None
    wanted = set(namespaces)
    pids = [pid for name, found in netns.ns_pids().items() if name in wanted for pid in found]
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and any(_running(pid) for pid in pids):
        time.sleep(0.02)
    return pids


def _running(pid: int) -> bool:
    """Alive and not a zombie (a zombie has left its namespace's resources)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rpartition(")")[2].split()[0] != "Z"


def remove_namespace(name: str) -> None:
    assert netns is not None
    if name in netns.listnetns():
        netns.remove(name)


# ------------------------------------------------------------------------------ the lab


@dataclass
class RobotLink:
    """One robot's place in the lab."""

    name: str
    index: int
    namespace: str
    #: its end of the veth, in its namespace
    interface: str
    #: the access point's end, a port of bridge ``b<subnet>``
    ap_interface: str
    state: LinkState = CLEAN

    @property
    def address(self) -> str:
        return robot_address(self.index, self.state.subnet)

    @property
    def up_chain(self) -> str:
        return f"up_r{self.index}"

    @property
    def down_chain(self) -> str:
        return f"down_r{self.index}"


@dataclass(frozen=True)
class LinkCounters:
    """Frames the lab's nftables chains saw and dropped on one robot's link since it was
    built: ``up`` = robot -> access point, ``down`` = access point -> robot."""

    up_seen: int
    up_dropped: int
    down_seen: int
    down_dropped: int


class Lab:
    """A built lab. ``Lab.create(robots)`` builds it; ``close()`` (or leaving the ``with``)
    removes everything on every path. Thread-safe: a profile runner may change links while the
    caller reads counters."""

    def __init__(self, names: LabNames, robots: list[str], timeline: Timeline) -> None:
        self.names = names
        self.timeline = timeline
        self.robots: dict[str, RobotLink] = {
            name: RobotLink(
                name,
                index,
                names.namespace(name),
                names.robot_if(index),
                names.robot_ap_if(index),
            )
            for index, name in enumerate(robots, start=1)
        }
        self._ip = tool("ip")
        self._nft = tool("nft")
        self._lock = threading.RLock()
        self._namespaces: list[str] = []
        self._procs: list[Proc] = []
        self._owner: Path | None = None
        self._closed = False

    # ---------------------------------------------------------------- building

    @classmethod
    def create(cls, robots: int | Sequence[str], *, timeline: Timeline | None = None) -> Lab:
        """Build a lab with ``robots`` (a count: robot1..robotN, or names) on access point 0,
        links clean. Raises LabUnavailable when the machine cannot, LabError when a step
        failed (after removing what was built)."""
        check_available()
        if isinstance(robots, int):
            robots = [f"robot{i}" for i in range(1, robots + 1)]
        names = list(robots)
        try:
            check_robot_names(names)
        except ValueError as exc:
            raise LabError(str(exc)) from None
        lab = cls(LabNames(new_lab_id()), names, timeline or Timeline())
        try:
            lab._build()
        except BaseException as exc:
            with contextlib.suppress(Exception):
                lab.close()
            if isinstance(exc, PermissionError):
                raise LabUnavailable(f"the kernel lab was refused by the kernel: {exc}") from exc
            if isinstance(exc, LabError | KeyboardInterrupt | SystemExit):
                raise
            raise LabError(f"building lab {lab.names.lab_id} failed: {exc!r}") from exc
        return lab

    def _new_namespace(self, name: str) -> None:
        assert netns is not None
        self._namespaces.append(name)  # before: a half-made one is removed too
        netns.create(name)

    def _build(self) -> None:
        names = self.names
        self._owner = write_owner(names.lab_id)
        for namespace in (names.ap, names.ceddp, *(r.namespace for r in self.robots.values())):
            self._new_namespace(namespace)
        with netlink(names.ap) as ap:
            _up(ap, "lo")
            for subnet in (0, 1):
                ap.link("add", ifname=names.bridge(subnet), kind="bridge")
                index = _up(ap, names.bridge(subnet))
                ap.addr("add", index=index, address=gateway(subnet), prefixlen=PREFIXLEN)
            ceddp_if = names.interface("c")
            ap.link(
                "add",
                ifname=names.interface("ca"),
                kind="veth",
                peer={"ifname": ceddp_if, "net_ns_fd": names.ceddp},
            )
            index = _up(ap, names.interface("ca"))
            ap.addr("add", index=index, address=AP_SERVER_ADDRESS, prefixlen=PREFIXLEN)
            bridge = _index(ap, names.bridge(0))
            for robot in self.robots.values():
                ap.link(
                    "add",
                    ifname=robot.ap_interface,
                    kind="veth",
                    peer={"ifname": robot.interface, "net_ns_fd": robot.namespace},
                )
                ap.link("set", index=_index(ap, robot.ap_interface), master=bridge)
                _up(ap, robot.ap_interface)
        # the access point routes between its subnets and the server's (/proc/sys/net is the
        # opening thread's namespace's)
        in_namespace(names.ap, lambda: Path("/proc/sys/net/ipv4/ip_forward").write_text("1"))
        self._address(names.ceddp, ceddp_if, CEDDP_ADDRESS, AP_SERVER_ADDRESS)
        for robot in self.robots.values():
            self._address(robot.namespace, robot.interface, robot.address, gateway(0))
            self._nft_in(robot.namespace, nft.table_ruleset({robot.down_chain: robot.interface}))
        self._nft_in(
            names.ap,
            nft.table_ruleset({r.up_chain: r.ap_interface for r in self.robots.values()}),
        )
        self.timeline.record(
            "lab_up",
            lab_id=names.lab_id,
            namespaces=list(self._namespaces),
            ceddp_address=CEDDP_ADDRESS,
            robots={r.name: r.address for r in self.robots.values()},
        )

    def _address(self, namespace: str, ifname: str, address: str, via: str) -> None:
        with netlink(namespace) as ipr:
            _up(ipr, "lo")
            index = _up(ipr, ifname)
            ipr.addr("add", index=index, address=address, prefixlen=PREFIXLEN)
            ipr.route("replace", dst="0.0.0.0/0", gateway=via, prefsrc=address)

    # ---------------------------------------------------------------- what callers use

    @property
    def lab_id(self) -> str:
        return self.names.lab_id

    @property
    def ceddp_namespace(self) -> str:
        return self.names.ceddp

    @property
    def ceddp_address(self) -> str:
        return CEDDP_ADDRESS

    @property
    def namespaces(self) -> list[str]:
        return list(self._namespaces)

    def robot(self, name: str) -> RobotLink:
        try:
            return self.robots[name]
        except KeyError:
            raise LabError(f"no robot {name!r} in lab {self.lab_id}") from None

    def spawn(
        self,
        name: str,
        namespace: str,
        args: list[str],
        workdir: Path,
        *,
        log: bool = True,
        env: dict[str, str] | None = None,
    ) -> Proc:
        """``python ARGS`` inside ``namespace`` as an ``arpz.tools.launch.Proc`` (its log, its pid);
        killed at ``close()`` if still running."""
        proc = Proc.spawn(
            name, ["-c", _IN_NETNS, self._ip, namespace, *args], workdir, log=log, env=env
        )
        with self._lock:
            self._procs.append(proc)
        return proc

    def run(
        self, namespace: str, argv: list[str], *, input: str | None = None
    ) -> subprocess.CompletedProcess[str]:
        """Run a command inside ``namespace`` to its end; LabError if it fails."""
        done = subprocess.run(
            [self._ip, "netns", "exec", namespace, *argv],
            input=input,
            capture_output=True,
            text=True,
            timeout=COMMAND_TIMEOUT_S,
            check=False,
        )
        if done.returncode != 0:
            raise LabError(
                f"`{' '.join(argv)}` in {namespace} failed ({done.returncode}): "
                f"{done.stderr.strip()}"
            )
        return done

    def socket(
        self, namespace: str, family: int = socket.AF_INET, kind: int = socket.SOCK_DGRAM
    ) -> socket.socket:
        """A socket that lives in ``namespace`` (usable from this process, any thread)."""
        return in_namespace(namespace, lambda: socket.socket(family, kind))

    def apply(self, robot: str, state: LinkState, cause: str = "set") -> None:
        """Make ``robot``'s link ``state`` now (only what changed is touched) and record it
        in the timeline."""
        with self._lock:
            link = self.robot(robot)
            old = link.state
            if (old.loss_up_pct, old.dead) != (state.loss_up_pct, state.dead):
                self._nft_in(
                    self.names.ap,
                    nft.chain_update(link.up_chain, loss_pct=state.loss_up_pct, dead=state.dead),
                )
            if (old.loss_down_pct, old.dead) != (state.loss_down_pct, state.dead):
                self._nft_in(
                    link.namespace,
                    nft.chain_update(
                        link.down_chain, loss_pct=state.loss_down_pct, dead=state.dead
                    ),
                )
            if old.rate_kbit != state.rate_kbit:
                self._rate(link.namespace, link.interface, state.rate_kbit)
                self._rate(self.names.ap, link.ap_interface, state.rate_kbit)
            if old.subnet != state.subnet:
                self._roam(link, state.subnet)
            link.state = state
            self.timeline.link(robot, state, cause, link.address)

    def counters(self, robot: str) -> LinkCounters:
        link = self.robot(robot)
        up = self._counters(self.names.ap)
        down = self._counters(link.namespace)
        return LinkCounters(
            up_seen=up.get(nft.seen_counter(link.up_chain), 0),
            up_dropped=up.get(nft.dropped_counter(link.up_chain), 0),
            down_seen=down.get(nft.seen_counter(link.down_chain), 0),
            down_dropped=down.get(nft.dropped_counter(link.down_chain), 0),
        )

    # ---------------------------------------------------------------- the changes

    def _nft_in(self, namespace: str, ruleset: str) -> None:
        self.run(namespace, [self._nft, "-f", "-"], input=ruleset)

    def _counters(self, namespace: str) -> dict[str, int]:
        done = self.run(
            namespace, [self._nft, "-j", "list", "counters", "table", "netdev", NFT_TABLE]
        )
        return nft.parse_counters(json.loads(done.stdout))

    def _rate(self, namespace: str, ifname: str, kbit: int | None) -> None:
        """tbf on ``ifname``'s egress (the sending end of its direction), or none."""
        with netlink(namespace) as ipr:
            index = _index(ipr, ifname)
            if kbit is None:
                ipr.tc("del", index=index, root=True)
            else:
                ipr.tc(
                    "replace",
                    "tbf",
                    index,
                    0x10000,
                    rate=f"{kbit}kbit",
                    burst=tbf_burst_bytes(kbit),
                    latency=TBF_LATENCY,
                )

    def _roam(self, link: RobotLink, subnet: int) -> None:
        """Move the robot to access point ``subnet``: its port to the other bridge, a new
        address, a new default route whose source is the new address."""
        old, new = link.address, robot_address(link.index, subnet)
        with netlink(self.names.ap) as ap:
            ap.link(
                "set",
                index=_index(ap, link.ap_interface),
                master=_index(ap, self.names.bridge(subnet)),
            )
        with netlink(link.namespace) as ipr:
            index = _index(ipr, link.interface)
            ipr.addr("del", index=index, address=old, prefixlen=PREFIXLEN)
            ipr.addr("add", index=index, address=new, prefixlen=PREFIXLEN)
            ipr.route("replace", dst="0.0.0.0/0", gateway=gateway(subnet), prefsrc=new)

    # ---------------------------------------------------------------- teardown

    def close(self) -> None:
        """Kill what runs inside, remove every namespace (their links and nftables tables go
        with them) and the owner file. Safe to call twice; raises LabError if something could
        not be removed (after trying everything)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            procs, self._procs = self._procs, []
        problems = []
        for proc in procs:
            try:
                proc.kill()
            except Exception as exc:
                problems.append(f"killing {proc.name}: {exc!r}")
        if netns is not None:
            mine = [n for n in netns.listnetns() if n.startswith(self.names.namespace(""))]
            namespaces = list(dict.fromkeys([*self._namespaces, *mine]))
            try:
                kill_pids_in(namespaces)
            except Exception as exc:
                problems.append(f"killing what runs in the lab: {exc!r}")
            for name in namespaces:
                try:
                    remove_namespace(name)
                except Exception as exc:
                    problems.append(f"removing namespace {name}: {exc!r}")
        if self._owner is not None:
            self._owner.unlink(missing_ok=True)
        self.timeline.record("lab_down", lab_id=self.lab_id, problems=problems)
        if problems:
            raise LabError(f"lab {self.lab_id} teardown: " + "; ".join(problems))

    def __enter__(self) -> Lab:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc is None:
            self.close()
            return
        try:
            self.close()
        except LabError as problem:  # the body's own exception stays the one raised
            exc.add_note(str(problem))


def tbf_burst_bytes(kbit: int) -> int:
    """tbf's bucket: 20 ms at the rate, at least 4 KiB (a few full frames)."""
    return max(4096, kbit * 1000 // 8 // 50)


def _index(ipr: Any, ifname: str) -> int:
    found = ipr.link_lookup(ifname=ifname)
    if not found:
        raise LabError(f"no interface {ifname}")
    return int(found[0])


def _up(ipr: Any, ifname: str) -> int:
    index = _index(ipr, ifname)
    ipr.link("set", index=index, state="up")
    return index


@contextlib.contextmanager
def interrupt_on_signals() -> Iterator[None]:
    """While inside, SIGINT and SIGTERM raise LabInterrupted in the main thread, so a ``with
    Lab.create(...)`` inside tears the lab down (SIGTERM's default action ends a process
    without running any ``finally``). The previous handlers come back on the way out."""

    def interrupt(signum: int, _frame: object) -> None:
        raise LabInterrupted(f"stopped by {signal.Signals(signum).name}")

    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
