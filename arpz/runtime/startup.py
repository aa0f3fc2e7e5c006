"""What every long-running arpz process does the same way at start-up."""

from __future__ import annotations

import argparse
import faulthandler
import json
import logging
import signal
import sys
import threading
import time
from pathlib import Path

from arpz.core.endpoints import DEFAULT_CONNECT, check_endpoints
from arpz.core.errors import ConfigError
from arpz.core.version import version_line


def configure_logging(level: str) -> None:
    logging.basicConfig(
        level=level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM: both are a clean stop (final reports, flushed files,
    closed Zenoh sessions), never an abrupt exit.

    The main thread waits for it with ``wait_for_stop``, or with timed waits of its own, never
    with ``stop.wait()``: see ``wait_for_stop``."""
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


def wait_for_stop(
    stop: threading.Event, timeout_s: float | None = None, *, poll_s: float = 0.2
) -> bool:
    """Block the main thread until ``stop`` is set (or ``timeout_s`` passed), in timed waits;
    True when ``stop`` is set.

    Python runs a signal's handler on the main thread only, at its next bytecode. When the
    kernel delivers the signal to another thread (a process with Zenoh sessions and writers has
    hundreds), a main thread blocked in an untimed ``stop.wait()`` never gets there and the
    process ignores SIGINT (seen: 2 of 4 workers of a 50-robot fleet run, killed after 70 s,
    their robots' final reports lost); a long timed one gets there late. A wait here returns to
    bytecode every ``poll_s``."""
    if not poll_s > 0:
        raise ValueError(f"poll_s must be > 0 (a zero wait spins), got {poll_s}")
    end = None if timeout_s is None else time.monotonic() + timeout_s
    while True:
        step = poll_s if end is None else min(poll_s, end - time.monotonic())
        if step <= 0:
            return stop.is_set()
        if stop.wait(step):
            return True


# --- the options and conventions every command shares (docs/tools.md "Conventions") ---------

#: ``--json`` alone prints machine-readable output on stdout; ``--json FILE`` writes it there
JSON_TO_STDOUT = "-"


def add_json_option(parser: argparse.ArgumentParser, what: str = "the result") -> None:
    """One meaning of ``--json`` in every command, so that no user has to remember which tool
    prints and which one writes a file."""
    parser.add_argument(
        "--json",
        nargs="?",
        const=JSON_TO_STDOUT,
        default=None,
        metavar="FILE",
        help=f"{what} as JSON: on stdout, or into FILE when given",
    )


def emit_json(document: object, target: str | None) -> None:
    """Print or write ``document`` as ``--json`` asked (nothing when it was not given)."""
    if target is None:
        return
    text = json.dumps(document, indent=2, sort_keys=True, default=str)
    if target == JSON_TO_STDOUT:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()
    else:
        Path(target).write_text(text + "\n", encoding="utf-8")


def add_fleet_client_options(
    parser: argparse.ArgumentParser,
    *,
    fleet_default: str | None = "default",
    fleet_help: str = "the fleet's name (default 'default')",
) -> None:
    """``--connect`` / ``--fleet`` / ``--zenoh-config`` of every tool that joins a running fleet
    as a client, as robots and ROS 2 tools do."""
    parser.add_argument(
        "--connect",
        default=",".join(DEFAULT_CONNECT),
        metavar="ENDPOINT[,ENDPOINT...]",
        help=f"the fleet's router (default {','.join(DEFAULT_CONNECT)})",
    )
    parser.add_argument("--fleet", default=fleet_default, help=fleet_help)
    parser.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE",
        help="a Zenoh JSON5 config applied to the session before arpz's own settings",
    )


def connect_endpoints(value: str, flag: str = "--connect") -> tuple[str, ...]:
    """The endpoints of a ``--connect`` value, each checked: a bad one is a ConfigError naming
    the flag (exit 2), never a raw Zenoh parse error."""
    endpoints = [part.strip() for part in value.split(",") if part.strip()]
    if not endpoints:
        raise ConfigError(f"{flag}: give at least one endpoint, e.g. 'tcp/192.168.1.10:7447'")
    try:
        check_endpoints(endpoints, field=flag)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    return tuple(endpoints)


def fail(tool: str, message: str, code: int = 2) -> int:
    """The one error format of every command: ``arpz TOOL: error: MESSAGE`` on stderr; returns
    the exit code (2: the user's input or configuration, 1: the run failed)."""
    print(f"arpz {tool}: error: {message}", file=sys.stderr)
    return code


def add_version_option(parser: argparse.ArgumentParser) -> None:
    """``--version`` on every command: which arpz and which Zenoh, the first question of any
    bug report (and of ``arpz doctor``)."""
    parser.add_argument("--version", action="version", version=version_line())
