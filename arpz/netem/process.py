"""Run ``python -m arpz.netem`` as a child process (tests, benchmarks, experiments).

A separate process keeps the proxy's timing independent of the GIL of the process under test.
"""

from __future__ import annotations

import json
import select
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


class NetemProcess:
    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.report: dict[str, Any] | None = None

    def stop(self, timeout_s: float = 10.0) -> dict[str, Any] | None:
        """SIGTERM, then the counters it prints on exit (None if it had to be killed)."""
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            out, _ = self.proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()
            return None
        lines = [line for line in out.splitlines() if line.startswith("{")]
        self.report = json.loads(lines[-1]) if lines else None
        return self.report


@contextmanager
def netem_process(
    listen: str, forward: str, *args: str, ready_timeout_s: float = 10.0
) -> Iterator[NetemProcess]:
    """Start the proxy, wait for its "ready" line, and always stop (or kill) it on exit."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "arpz.netem", "--listen", listen, "--forward", forward, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    handle = NetemProcess(proc)
    try:
        assert proc.stderr is not None
        readable, _, _ = select.select([proc.stderr], [], [], ready_timeout_s)
        line = proc.stderr.readline() if readable else "(no output)"
        if "ready" not in line:
            raise RuntimeError(f"arpz.netem did not start: {line}{proc.stderr.read()}")
        yield handle
    finally:
        handle.stop()
        if proc.stderr is not None:
            proc.stderr.close()
