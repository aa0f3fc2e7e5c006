"""Run the perf tool's processes (router, sub, pub, ping, pong) for benchmarks and tests.

Every child is stopped (SIGTERM, then SIGKILL) on every exit path, so a failed run never leaves a
router or a subscriber behind.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from typing import IO, Any

from arpz.tools.launch import free_port  # re-exported: benchmarks and tests import it from here


def _perf(*args: str) -> list[str]:
    return [sys.executable, "-m", "arpz.perf", *args]


class Child(subprocess.Popen[str]):
    """A child process whose stderr goes to a temporary file, not a pipe: a pipe that nobody
    reads after "ready" fills at 64 KiB and then blocks whichever thread of the child logs next
    (a reliable reader logging a traceback per sample stopped acknowledging that way)."""

    def __init__(self, argv: Sequence[str]) -> None:
        # closed by ``child`` when the process has ended
        self.stderr_file: IO[str] = tempfile.TemporaryFile("w+", encoding="utf-8")  # noqa: SIM115
        super().__init__(list(argv), stdout=subprocess.PIPE, stderr=self.stderr_file, text=True)

    def stderr_text(self) -> str:
        """Everything the child has written to stderr so far."""
        # pread: the child shares this file's offset, which a read or a seek here would move
        fd, chunks, at = self.stderr_file.fileno(), [], 0
        while chunk := os.pread(fd, 1 << 16, at):
            chunks.append(chunk)
            at += len(chunk)
        return b"".join(chunks).decode("utf-8", errors="replace")


@contextmanager
def child(
    argv: Sequence[str], ready: str | None = None, timeout_s: float = 20.0
) -> Iterator[Child]:
    """Start a process; if ``ready`` is given, wait (polling) for that text on its stderr."""
    proc = Child(argv)
    try:
        if ready is not None:
            end = time.monotonic() + timeout_s
            while ready not in (seen := proc.stderr_text()):
                if time.monotonic() > end or proc.poll() is not None:
                    raise RuntimeError(f"{' '.join(argv)} not ready: {seen[-2000:]}")
                time.sleep(0.01)
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
        proc.stderr_file.close()


def last_json(proc: Child, timeout_s: float) -> dict[str, Any]:
    """Wait for the process and return the last JSON line it printed."""
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        raise RuntimeError(f"timed out; stderr: {proc.stderr_text()[-2000:]}") from None
    lines = [line for line in out.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"exit {proc.returncode}; stderr: {proc.stderr_text()[-2000:]}")
    result: dict[str, Any] = json.loads(lines[-1])
    return result


@contextmanager
def perf_router(*listen: str, zenoh_config: str | None = None) -> Iterator[None]:
    """A bare router; ``zenoh_config``: its ``--zenoh-config`` file."""
    extra = ["--zenoh-config", zenoh_config] if zenoh_config else []
    with child(_perf("router", "--listen", ",".join(listen), *extra), ready="listening"):
        yield


def _flags(key: str, transport: str, size: int) -> list[str]:
    return ["--key", key, "--transport", transport, "--size", str(size)]


def pubsub(
    *,
    transport: str,
    pub_connect: str,
    sub_connect: str,
    count: int,
    rate_hz: float = 0.0,
    size: int = 24,
    extra: Sequence[str] = (),
    timeout_s: float = 120.0,
    key: str = "perf/topic",
) -> tuple[dict[str, Any], dict[str, Any]]:
    """One publisher process and one subscriber process; returns (pub result, sub report)."""
    common = [*_flags(key, transport, size), "--rate", str(rate_hz), *extra]
    with ExitStack() as stack:
        sub = stack.enter_context(
            child(
                _perf("sub", "--connect", sub_connect, "--count", str(count), *common),
                ready="ready",
            )
        )
        pub = stack.enter_context(
            child(_perf("pub", "--connect", pub_connect, "--count", str(count), *common))
        )
        pub_result = last_json(pub, timeout_s)
        sub_report = last_json(sub, timeout_s)
    return pub_result, sub_report


def pingpong(
    *,
    transport: str,
    connect: str,
    count: int,
    rate_hz: float = 1000.0,
    size: int = 24,
    extra: Sequence[str] = (),
    timeout_s: float = 120.0,
    key: str = "perf/rtt",
) -> dict[str, Any]:
    common = ["--connect", connect, *_flags(key, transport, size), *extra]
    ping_args = _perf("ping", *common, "--count", str(count), "--rate", str(rate_hz))
    with child(_perf("pong", *common), ready="ready"), child(ping_args) as ping:
        return last_json(ping, timeout_s)


@contextmanager
def lossy_setup(loss_pct: float, clean_s: float, *netem_args: str) -> Iterator[tuple[str, str]]:
    """A router (UDP + TCP), and a netem proxy in front of its UDP endpoint losing ``loss_pct`` %
    each way after ``clean_s``; yields (lossy udp endpoint for the publisher, tcp endpoint)."""
    from arpz.netem.process import netem_process  # the perf tool itself does not need netem

    udp, tcp, proxy = free_port(socket.SOCK_DGRAM), free_port(), free_port(socket.SOCK_DGRAM)
    with (
        perf_router(f"udp/127.0.0.1:{udp}", f"tcp/127.0.0.1:{tcp}"),
        netem_process(
            f"udp/127.0.0.1:{proxy}",
            f"udp/127.0.0.1:{udp}",
            "--loss",
            str(loss_pct),
            "--clean-s",
            str(clean_s),
            *netem_args,
        ),
    ):
        yield f"udp/127.0.0.1:{proxy}", f"tcp/127.0.0.1:{tcp}"
