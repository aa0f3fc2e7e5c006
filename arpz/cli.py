"""What every long-running arpz process does the same way at start-up."""

from __future__ import annotations

import faulthandler
import logging
import signal
import threading


def configure_logging(level: str) -> None:
    logging.basicConfig(
        level=level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM: both are a clean stop (final reports, flushed files,
    closed Zenoh sessions), never an abrupt exit."""
    stop = threading.Event()

    def on_signal(*_: object) -> None:
        # Never ``stop.set()`` here: the handler runs on the main thread between two bytecodes,
        # possibly inside ``stop.wait()`` while it holds the event's own (non-reentrant) lock,
        # and ``set`` would then wait for that lock forever (seen: a robot that ignored SIGINT).
        threading.Thread(target=stop.set, name="arpz-signal", daemon=True).start()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    # SIGUSR1 prints every thread's Python stack to stderr, even while the main thread is stuck
    # in native code (where the handlers above cannot run): `kill -USR1 PID` on a hung process
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    return stop
