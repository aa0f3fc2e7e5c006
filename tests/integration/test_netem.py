"""The lossy-link emulator as a process, with a real Zenoh client over ``udp/`` through it."""

from __future__ import annotations

import itertools
import signal
import subprocess
import sys
import time

import pytest

from arpz.core.transport import SessionSettings
from arpz.netem.process import netem_process
from arpz.transport.zenoh import ZenohTransport
from tests.support import free_port, free_udp_port, wait_until

pytestmark = pytest.mark.integration


def _router(udp: int, tcp: int) -> ZenohTransport:
    return ZenohTransport.open(
        SessionSettings(mode="router", listen=[f"udp/127.0.0.1:{udp}", f"tcp/127.0.0.1:{tcp}"])
    )


def test_loss_through_the_proxy_matches_the_setting_and_the_counters_add_up() -> None:
    udp, tcp, proxy = free_udp_port(), free_port(), free_udp_port()
    got: list[bytes] = []
    with (
        _router(udp, tcp),
        netem_process(
            f"udp/127.0.0.1:{proxy}",
            f"udp/127.0.0.1:{udp}",
            "--loss",
            "20",
            "--clean-s",
            "1.5",
            "--direction",
            "up",
            "--seed",
            "3",
        ) as netem,
    ):
        lossy_from = time.monotonic() + 1.5  # the proxy's clock started before it said "ready"
        with (
            ZenohTransport.open(
                SessionSettings(connect=[f"udp/127.0.0.1:{proxy}"]), timeout_s=5
            ) as a,
            ZenohTransport.open(
                SessionSettings(connect=[f"tcp/127.0.0.1:{tcp}"]), timeout_s=5
            ) as b,
        ):
            b.subscribe("t", lambda k, p, att: got.append(p))
            pub = a.publisher("t", express=True)  # one sample per datagram
            wait_until(lambda: (pub.put(b"probe"), bool(got))[1], what="link up")
            time.sleep(max(0.0, lossy_from - time.monotonic()))  # past the clean period
            got.clear()
            for i in range(1000):
                pub.put(b"%d" % i)
                time.sleep(0.001)
            time.sleep(0.3)
        report = netem.stop()
    assert report is not None
    up = report["up"]
    assert up["received"] == up["forwarded"] + up["dropped"]
    assert abs(1 - len(got) / 1000 - 0.2) < 0.06
    assert up["dropped_loss"] >= 1000 - len(got)


def test_scheduled_outage_drops_everything_for_its_duration() -> None:
    udp, tcp, proxy = free_udp_port(), free_port(), free_udp_port()
    got: list[float] = []
    with (
        _router(udp, tcp),
        netem_process(
            f"udp/127.0.0.1:{proxy}",
            f"udp/127.0.0.1:{udp}",
            "--outage",
            "1.0:0.5",
        ) as netem,
    ):
        t0 = time.monotonic()
        with (
            ZenohTransport.open(
                SessionSettings(connect=[f"udp/127.0.0.1:{proxy}"]), timeout_s=5
            ) as a,
            ZenohTransport.open(
                SessionSettings(connect=[f"tcp/127.0.0.1:{tcp}"]), timeout_s=5
            ) as b,
        ):
            b.subscribe("t", lambda k, p, att: got.append(time.monotonic() - t0))
            pub = a.publisher("t", express=True)
            while time.monotonic() - t0 < 2.2:
                pub.put(b"x")
                time.sleep(0.005)
        report = netem.stop()
    assert report is not None and report["up"]["dropped_outage"] > 50
    gaps = [b - a for a, b in itertools.pairwise(got)]
    assert 0.4 < max(gaps) < 0.8  # one silence of about the outage, the session survived it
    assert got[-1] > 1.9


def test_duration_ends_the_process_and_prints_counters() -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "arpz.netem",
            "--listen",
            f"udp/127.0.0.1:{free_udp_port()}",
            "--forward",
            f"udp/127.0.0.1:{free_udp_port()}",
            "--duration",
            "0.3",
            "--loss",
            "5",
        ],
        capture_output=True,
        text=True,
        timeout=20,
        check=True,
    )
    assert '"up"' in out.stdout and "arpz.netem up: received 0" in out.stderr


def test_sigterm_exits_cleanly_and_bad_arguments_say_why() -> None:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "arpz.netem",
            "--listen",
            f"udp/127.0.0.1:{free_udp_port()}",
            "--forward",
            f"udp/127.0.0.1:{free_udp_port()}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None and "ready" in proc.stderr.readline()
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=10)
        assert proc.returncode == 0 and '"down"' in out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    bad = subprocess.run(
        [sys.executable, "-m", "arpz.netem", "--listen", "127.0.0.1", "--forward", "udp/x:1"],
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert bad.returncode == 2 and "udp/HOST:PORT" in bad.stderr


def test_datagrams_the_kernel_drops_before_the_proxy_reads_them_are_counted() -> None:
    """A burst larger than the proxy's receive buffer (its thread not running here) is lost in
    the kernel, not by the emulated link: counted apart, as ``rx_overflow``."""
    import socket

    from arpz.netem import Impairments, NetemProxy

    port = free_udp_port()
    proxy = NetemProxy(f"udp/127.0.0.1:{port}", f"udp/127.0.0.1:{free_udp_port()}", Impairments())
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for _ in range(20_000):  # 28 MB: well past the 8 MiB asked for (x2 by the kernel)
            sender.sendto(b"x" * 1400, ("127.0.0.1", port))
        report = proxy.report()
        assert report.up.rx_overflow > 0 and report.up.received == 0
    finally:
        sender.close()
        proxy.request_stop()
        proxy.run()  # returns at once and closes the sockets
