"""The kernel lab for real: namespaces, an access point, nftables loss and dead zones, roaming,
tbf, teardown on every path, ``lab clean`` after a SIGKILL, and a CEDDP with a robot inside.

Root only: without CAP_NET_ADMIN (or ``nft``) every test here skips with the reason, unless
``ARPZ_REQUIRE_LAB=1`` (CI) turns the skip into a failure. Ports need no choosing: each lab's
namespaces have ports of their own, and nothing of a lab is visible outside it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from arpz.lab import (
    TIMELINE_FILE,
    Lab,
    LabRunOptions,
    LinkState,
    ProfileRunner,
    dead_zone,
    load,
    run_lab,
    spans,
)
from arpz.lab.clean import clean
from arpz.lab.names import IF_PREFIX, NS_PREFIX
from arpz.tools.demo import DemoOptions
from tests.lab_support import require_lab
from tests.support import wait_until

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
PORT = 9000


@pytest.fixture(autouse=True)
def lab_available() -> None:
    require_lab()


@pytest.fixture
def lab() -> Iterator[Lab]:
    with Lab.create(2) as built:
        yield built


def _left_over(lab_id: str) -> list[str]:
    """What of lab ``lab_id`` the kernel still has: namespaces, host interfaces."""
    namespaces = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True).stdout
    return [
        word
        for word in (namespaces + links).replace(":", " ").replace("@", " ").split()
        if word.startswith((f"{NS_PREFIX}{lab_id}-", f"{IF_PREFIX}{lab_id}"))
    ]


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
    except OSError:
        return False
    return state != "Z"


class UdpCounter:
    """Datagrams from a sender socket to a receiver socket (each in its namespace), with the
    receiver draining on a thread so its buffer never overflows: what is missing was dropped by
    the lab."""

    def __init__(self, sender: socket.socket, receiver: socket.socket, to: tuple[str, int]):
        self.sender, self.receiver, self.to = sender, receiver, to
        receiver.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        receiver.settimeout(0.15)
        #: (seq, monotonic time it was sent) of each datagram received
        self.received: list[tuple[int, float]] = []

    def run(self, count: int, interval_s: float = 0.0) -> list[float]:
        """Send ``count`` datagrams (``interval_s`` apart, else in bursts of 20); the send
        times. The receiver drains until 0.3 s after the last one."""
        self.received = []
        done = threading.Event()
        drain = threading.Thread(target=self._drain, args=(done,))
        drain.start()
        sent: list[float] = []
        try:
            for seq in range(count):
                now = time.monotonic()
                sent.append(now)
                self.sender.sendto(f"{seq} {now}".encode(), self.to)
                if interval_s:
                    time.sleep(interval_s)
                elif seq % 20 == 19:
                    time.sleep(0.001)
        finally:
            done.set()
            drain.join()
        return sent

    def _drain(self, done: threading.Event) -> None:
        quiet_since: float | None = None
        while True:
            try:
                data = self.receiver.recv(2048)
            except TimeoutError:
                if done.is_set():
                    if quiet_since is not None:
                        return
                    quiet_since = time.monotonic()  # one more quiet spell after the end
                continue
            seq, sent = data.decode().split()
            self.received.append((int(seq), float(sent)))


def test_loss_rules_drop_the_configured_share_each_way(lab: Lab) -> None:
    robot = lab.robot("robot1")
    with (
        lab.socket(lab.ceddp_namespace) as server,
        lab.socket(robot.namespace) as client,
    ):
        server.bind((lab.ceddp_address, PORT))
        client.bind((robot.address, PORT))
        up = UdpCounter(client, server, (lab.ceddp_address, PORT))
        down = UdpCounter(server, client, (robot.address, PORT))
        assert len(up.run(500)) == 500 and len(up.received) == 500  # clean: nothing lost
        before = lab.counters("robot1")
        lab.apply("robot1", LinkState(loss_up_pct=20.0, loss_down_pct=5.0))
        count = 5000
        up.run(count)
        down.run(count)
        after = lab.counters("robot1")
    up_share = 1 - len(up.received) / count
    down_share = 1 - len(down.received) / count
    # binomial standard deviation at 5000 draws: 0.57 % (20 %), 0.31 % (5 %)
    assert up_share == pytest.approx(0.20, abs=0.025), up_share
    assert down_share == pytest.approx(0.05, abs=0.015), down_share
    # the kernel's own counters say the same (they also see the odd ARP frame)
    dropped_up = after.up_dropped - before.up_dropped
    assert dropped_up == pytest.approx(count - len(up.received), abs=10)
    assert after.down_dropped - before.down_dropped == pytest.approx(
        count - len(down.received), abs=10
    )
    print(f"lab loss: up {up_share:.2%} (20 % set), down {down_share:.2%} (5 % set)")


def test_a_dead_zone_drops_everything_then_the_link_recovers(lab: Lab) -> None:
    robot = lab.robot("robot2")
    runner = ProfileRunner(lab, {"robot2": dead_zone(1.5, at_s=1.0)})
    with (
        lab.socket(lab.ceddp_namespace) as server,
        lab.socket(robot.namespace) as client,
    ):
        server.bind((lab.ceddp_address, PORT))
        counter = UdpCounter(client, server, (lab.ceddp_address, PORT))
        runner.start()
        try:
            sent = counter.run(400, interval_s=0.01)  # 4 s and a bit, at 100 a second
        finally:
            runner.stop()
    [(start, end)] = spans(lab.timeline.entries, "robot2", lambda s: s.dead, clock="mono")
    assert end is not None and end - start == pytest.approx(1.5, abs=0.2)
    arrived = {seq for seq, _ in counter.received}
    before = [seq for seq, t in enumerate(sent) if t < start - 0.05]
    inside = [seq for seq, t in enumerate(sent) if start <= t <= end - 0.05]
    after = [seq for seq, t in enumerate(sent) if t > end]
    assert len(inside) > 100 and before and after
    assert arrived.isdisjoint(inside), sorted(arrived & set(inside))
    assert set(before) <= arrived and set(after) <= arrived


def test_roaming_moves_the_robot_to_the_other_subnet(lab: Lab) -> None:
    robot = lab.robot("robot1")
    old = robot.address
    lab.apply("robot1", LinkState(subnet=1), "roam")
    assert robot.address != old and robot.address.startswith("10.77.2.")
    shown = lab.run(robot.namespace, ["ip", "-4", "-o", "addr", "show"]).stdout
    route = lab.run(robot.namespace, ["ip", "route", "show", "default"]).stdout
    assert robot.address in shown and old not in shown
    assert "via 10.77.2.1" in route and f"src {robot.address}" in route
    # an echo through the new access point: the server sees the new address
    with (
        lab.socket(lab.ceddp_namespace) as server,
        lab.socket(robot.namespace) as client,
    ):
        server.bind((lab.ceddp_address, PORT))
        server.settimeout(5)
        client.settimeout(5)
        client.sendto(b"hello", (lab.ceddp_address, PORT))
        data, source = server.recvfrom(64)
        assert data == b"hello" and source[0] == robot.address
        server.sendto(b"back", source)
        assert client.recv(64) == b"back"
        # the old address is gone from the old subnet
        server.sendto(b"lost", (old, source[1]))
        client.settimeout(0.5)
        with pytest.raises(TimeoutError):
            client.recv(64)
    assert [e["address"] for e in lab.timeline.entries if e["event"] == "link"] == [robot.address]


def _tcp_mbit_s(lab: Lab, robot: str, seconds: float) -> float:
    """Bulk TCP from ``robot`` to the CEDDP's namespace for ``seconds``: Mbit/s received."""
    with (
        lab.socket(lab.ceddp_namespace, kind=socket.SOCK_STREAM) as listener,
        lab.socket(lab.robot(robot).namespace, kind=socket.SOCK_STREAM) as client,
    ):
        listener.bind((lab.ceddp_address, 0))
        listener.listen()
        received = [0]

        def sink() -> None:
            conn, _ = listener.accept()
            with conn:
                while data := conn.recv(1 << 16):
                    received[0] += len(data)

        thread = threading.Thread(target=sink)
        thread.start()
        client.connect(listener.getsockname())
        client.settimeout(0.2)
        start = time.monotonic()
        end = start + seconds
        chunk = b"x" * (1 << 16)
        while time.monotonic() < end:
            with contextlib.suppress(TimeoutError):  # the limit holds the sender back
                client.send(chunk)
        measured = received[0] * 8 / (time.monotonic() - start) / 1e6
        client.close()
        thread.join(timeout=10)
    return measured


def test_tbf_limits_the_throughput(lab: Lab) -> None:
    free = _tcp_mbit_s(lab, "robot1", 1.0)
    lab.apply("robot1", LinkState(rate_kbit=2000))
    limited = _tcp_mbit_s(lab, "robot1", 2.0)
    print(f"lab tbf: {free:.0f} Mbit/s free, {limited:.2f} Mbit/s at 2 mbit")
    assert free > 20, free
    assert 1.2 < limited < 2.3, limited
    shown = lab.run(lab.robot("robot1").namespace, ["tc", "qdisc", "show"]).stdout
    assert "tbf" in shown and "rate 2Mbit" in shown
    lab.apply("robot1", LinkState())
    assert "tbf" not in lab.run(lab.robot("robot1").namespace, ["tc", "qdisc", "show"]).stdout


def test_teardown_leaves_nothing_even_when_the_body_raises(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="the test's own failure"), Lab.create(1) as lab:
        lab_id = lab.lab_id
        sleeper = lab.spawn(
            "sleeper",
            lab.robot("robot1").namespace,
            ["-c", "import time; time.sleep(120)"],
            tmp_path,
            log=False,
        )
        # and one started behind the lab's back, in a namespace of it
        stray = subprocess.Popen(
            ["ip", "netns", "exec", lab.ceddp_namespace, "sleep", "120"],
        )
        assert _left_over(lab_id)
        raise RuntimeError("the test's own failure")
    try:
        assert _left_over(lab_id) == []
        assert not _alive(sleeper.popen.pid)
        wait_until(lambda: stray.poll() is not None, timeout_s=5, what="the stray process's end")
    finally:
        stray.kill()
        stray.wait()


def _child_with_a_lab(tmp_path: Path, *extra: str) -> tuple[subprocess.Popen[str], str, int]:
    """A Python process that builds a lab with a process inside and waits; its lab's id and
    the pid of the process inside."""
    script = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from arpz.lab import Lab, interrupt_on_signals\n"
        "with interrupt_on_signals(), Lab.create(1) as lab:\n"
        "    p = lab.spawn('s', lab.robot('robot1').namespace,"
        " ['-c', 'import time; time.sleep(120)'], Path(sys.argv[1]), log=False)\n"
        "    print(lab.lab_id, p.popen.pid, flush=True)\n"
        "    time.sleep(120)\n"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", script, str(tmp_path), *extra],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert child.stdout is not None
    line = child.stdout.readline().split()
    assert len(line) == 2, f"the child printed {line!r} (exit {child.poll()})"
    return child, line[0], int(line[1])


def _end(child: subprocess.Popen[str]) -> None:
    child.kill()
    child.wait()
    if child.stdout is not None:
        child.stdout.close()


def test_lab_clean_removes_a_lab_left_by_a_sigkilled_process(tmp_path: Path, lab: Lab) -> None:
    child, lab_id, inside = _child_with_a_lab(tmp_path)
    try:
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=10)
        assert _left_over(lab_id) and _alive(inside)  # what a killed run leaves
        done = subprocess.run(
            [sys.executable, "-m", "arpz", "lab", "clean"],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=ROOT,
        )
        assert done.returncode == 0, done.stderr
        assert lab_id in done.stdout, done.stdout
        assert _left_over(lab_id) == []
        wait_until(lambda: not _alive(inside), timeout_s=5, what="the process inside to end")
        # a lab whose owner runs (this test's) is left alone
        [removed] = [line for line in done.stdout.splitlines() if "removed" in line]
        assert lab.lab_id not in removed and _left_over(lab.lab_id)
    finally:
        _end(child)
        if _alive(inside):
            os.kill(inside, signal.SIGKILL)
        if _left_over(lab_id):
            clean()  # what the test should have seen done, not left for the next run


def test_sigterm_tears_the_lab_down(tmp_path: Path) -> None:
    child, lab_id, inside = _child_with_a_lab(tmp_path)
    try:
        child.send_signal(signal.SIGTERM)
        assert child.wait(timeout=30) != 0  # LabInterrupted ended it, after the teardown
        assert _left_over(lab_id) == []
        assert not _alive(inside)
    finally:
        _end(child)


def test_a_robot_joins_the_ceddp_inside_the_lab(tmp_path: Path) -> None:
    """``arpz lab run``'s path: the demo's configs, the real processes in their namespaces,
    a profile applied, the timeline beside the summary."""
    options = LabRunOptions(
        robots=1,
        link="tcp",
        duration_s=4.0,
        profiles=("robot1=loss-1",),
        demo=DemoOptions(rate_hz=20.0, rmax_hz=0.0),
    )
    result = run_lab(options, tmp_path)
    assert "robot robot1 joined" in (tmp_path / "ceddp.log").read_text()
    row = result.summary["robots"]["robot1"]
    assert row["received"] > 0 and row["final_stats"], row
    assert result.problems == []
    assert result.timeline == tmp_path / TIMELINE_FILE
    assert (tmp_path / "summary.json").exists()
    entries = load(result.timeline)
    events = [e["event"] for e in entries]
    assert events[0] == "lab_up" and events[-1] == "lab_down" and "profile" in events
    [(at, _)] = [(e["t"], e) for e in entries if e["event"] == "link" and e["loss_up_pct"] == 1.0]
    assert at == pytest.approx(0.0, abs=0.5)
    assert result.counters["robot1"].up_seen > 0
