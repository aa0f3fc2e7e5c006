"""SIGINT stops a process even when the kernel hands it to a thread other than the main one.

A process with Zenoh sessions and reliable-channel endpoints has hundreds of threads, and the
kernel may deliver a process-directed signal to any of them. Python then runs the handler on the
main thread at its next bytecode, which a main thread blocked in an untimed ``Event.wait()``
never reaches: 2 of the 4 workers of a 50-robot ``python -m arpz.perf fleet`` run ignored
SIGINT that way and were killed. ``signal.pthread_kill`` sends the signal to one chosen thread,
which makes the case deterministic."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import pytest

from arpz.runtime.startup import wait_for_stop

SCRIPT = r"""
import signal, sys, threading, time
from arpz.runtime.startup import stop_on_signals, wait_for_stop

stop = stop_on_signals()

def other_thread():
    time.sleep(0.3)  # the main thread is waiting by now
    signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # to this thread, not main
    time.sleep(60)

threading.Thread(target=other_thread, daemon=True).start()
if sys.argv[1] == "untimed":
    stop.wait()
else:
    wait_for_stop(stop)
print("stopped", flush=True)
"""


def _run(mode: str, timeout_s: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, timeout=timeout_s
    )


def test_wait_for_stop_sees_a_signal_delivered_to_another_thread() -> None:
    done = _run("wait_for_stop", timeout_s=20)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "stopped"


def test_an_untimed_wait_misses_it() -> None:
    """The case above is real: the same script with ``stop.wait()`` never stops."""
    with pytest.raises(subprocess.TimeoutExpired):
        _run("untimed", timeout_s=3)


def test_wait_for_stop_times_out_and_reports_the_stop() -> None:
    stop = threading.Event()
    start = time.monotonic()
    assert wait_for_stop(stop, 0.3, poll_s=0.05) is False
    assert 0.3 <= time.monotonic() - start < 2.0
    assert wait_for_stop(stop, -1.0) is False  # a deadline already past: no wait at all
    threading.Timer(0.1, stop.set).start()
    assert wait_for_stop(stop, 10.0) is True
    assert wait_for_stop(stop) is True


def test_wait_for_stop_refuses_a_poll_that_would_spin() -> None:
    with pytest.raises(ValueError, match="poll_s"):
        wait_for_stop(threading.Event(), 1.0, poll_s=0.0)
