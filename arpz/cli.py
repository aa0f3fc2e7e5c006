"""What every long-running arpz process does the same way at start-up."""

from __future__ import annotations

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
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop
