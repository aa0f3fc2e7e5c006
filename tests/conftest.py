"""Shared pytest wiring: the repository on sys.path, and callback assertions that fail the test.

The reliable channel catches whatever a user's callback raises (``on_data``, an event
callback), counts it in ``callback_errors`` and logs it on the ``arpz.reliability`` logger, so
that one bad callback cannot stop the channel. In a test that is the wrong trade: an ``assert``
inside ``on_data`` that fails would be swallowed, and the test would go on to time out waiting
for something that never comes, hiding the real message. The autouse fixture below listens on
that logger and fails the test with the original AssertionError and its traceback: as the
test's own failure when the assert fails while the test runs, as a teardown error when it fails
later (while fixtures close the channel).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import sys
import tempfile
import traceback
from collections.abc import Generator, Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

pytest_plugins = ["pytester"]

#: the logger the reliable channel reports a raising callback on (arpz/reliability/_channel.py)
CHANNEL_LOGGER = "arpz.reliability"
EXPECTED_MARKER = "callback_errors_expected"
#: the marker of a test that needs the machine's cores to itself (see ``cpu_share``)
CPU_EXCLUSIVE_MARKER = "cpu_exclusive"


def pytest_configure(config: pytest.Config) -> None:
    """Register the markers next to the code that reads them."""
    config.addinivalue_line(
        "markers",
        f"{CPU_EXCLUSIVE_MARKER}: a heavy or timing-bound test that runs with no other test "
        "beside it (the other test worker waits)",
    )
    config.addinivalue_line(
        "markers",
        f"{EXPECTED_MARKER}: the test makes a channel callback fail an assert on purpose; "
        "the callback-assertion check collects the failures but does not fail the test",
    )


class CallbackAssertions(logging.Handler):
    """Collects the records of the channel logger that carry an AssertionError."""

    def __init__(self) -> None:
        super().__init__(level=logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info is not None and isinstance(record.exc_info[1], AssertionError):
            self.records.append(record)

    def report(self) -> str:
        """Each collected assertion with the traceback of the callback that raised it."""
        parts = []
        for record in self.records:
            assert record.exc_info is not None and record.exc_info[0] is not None
            exc_type, exc, tb = record.exc_info
            text = "".join(traceback.format_exception(exc_type, exc, tb))
            parts.append(f"{record.getMessage()} (thread {record.threadName}):\n{text}")
        return "\n".join(parts)


_HANDLER = pytest.StashKey[CallbackAssertions]()


@pytest.fixture(autouse=True)
def callback_assertions(request: pytest.FixtureRequest) -> Iterator[CallbackAssertions]:
    """Fail the test if an assert inside a reliable-channel callback failed during it."""
    handler = CallbackAssertions()
    request.node.stash[_HANDLER] = handler
    logger = logging.getLogger(CHANNEL_LOGGER)
    logger.addHandler(handler)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
    if handler.records and request.node.get_closest_marker(EXPECTED_MARKER) is None:
        pytest.fail(
            f"{len(handler.records)} assertion(s) failed inside a reliable-channel callback "
            f"(the channel caught and logged them):\n{handler.report()}",
            pytrace=False,
        )


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Generator[None, object, object]:
    """Raise a callback's failed assert as the test's own failure.

    Whatever the test body raised meanwhile (typically a wait_until timeout) stays attached as
    the context of the original AssertionError."""
    try:
        return (yield)
    finally:
        handler = item.stash.get(_HANDLER, None)
        if (
            handler is not None
            and handler.records
            and item.get_closest_marker(EXPECTED_MARKER) is None
        ):
            record = handler.records.pop(0)  # any further ones fail the teardown
            assert record.exc_info is not None
            raise record.exc_info[1]  # type: ignore[misc]


@contextlib.contextmanager
def cpu_share(share: str) -> Iterator[None]:
    """Hold this test's share of the machine: none (a unit test), shared (an integration test)
    or whole (a ``cpu_exclusive`` one).

    The suite runs in two pytest-xdist workers on a 2-core machine. A heavy or timing-bound
    integration test (a fleet of robot processes, an overload, a latency bound) failed in CI
    whenever the other worker ran an integration test beside it (routers, robots, floods: more
    processes than cores), a different one each run. So the workers share a reader-writer lock
    (two ``flock`` files): integration tests take it shared and run two at a time; a
    ``cpu_exclusive`` test takes it exclusively, while the other worker waits before its next
    integration test. The turnstile makes a waiting exclusive test block new shared holders, so
    it cannot be starved. A unit test is one process and takes no lock, so the other worker runs
    the unit tests while the exclusive ones run (see ``pytest_collection_modifyitems``).
    Without xdist there is nobody to share with."""
    run_id = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run_id is None or share == SHARE_NONE:
        yield
        return
    exclusive = share == SHARE_WHOLE
    folder = Path(tempfile.gettempdir())
    with (
        open(folder / f"arpz-pytest-{run_id}.turnstile", "a") as turnstile,
        open(folder / f"arpz-pytest-{run_id}.cpu", "a") as cpu,
    ):
        mode = fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH
        fcntl.flock(turnstile, mode)
        fcntl.flock(cpu, mode)
        if not exclusive:
            fcntl.flock(turnstile, fcntl.LOCK_UN)  # let the next shared or exclusive one queue
        yield  # closing the files at the end of the with releases what is still held


SHARE_NONE, SHARE_SHARED, SHARE_WHOLE = "none", "shared", "whole"


def _share(item: pytest.Item) -> str:
    if item.get_closest_marker(CPU_EXCLUSIVE_MARKER) is not None:
        return SHARE_WHOLE
    if item.get_closest_marker("integration") is not None:
        return SHARE_SHARED
    return SHARE_NONE


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_protocol(item: pytest.Item) -> Generator[None, object, object]:
    """Run each test, setup to teardown, inside its share of the machine.

    ``tryfirst`` makes this the outermost wrapper, so the time a test waits for its share is not
    counted by pytest-timeout, whose timer starts inside it."""
    with cpu_share(_share(item)):
        return (yield)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Order the suite so that the exclusive tests overlap the unit tests, not idle time.

    xdist's ``load`` scheduling first hands each worker a chunk of consecutive tests (an eighth
    of the suite each), then more in collection order as they finish. With the exclusive tests
    first, one worker's chunk starts with all of them and the other worker's is unit tests, which
    it keeps taking while the exclusive ones run; the integration tests come last. (Not
    ``--dist loadgroup``: with pytest 9, pytest-xdist 3.8 sets its group suffix on a node id
    attribute pytest no longer reads, so ``xdist_group`` is silently ignored.)"""
    order = {SHARE_WHOLE: 0, SHARE_NONE: 1, SHARE_SHARED: 2}
    items.sort(key=lambda item: order[_share(item)])  # stable: files keep their order
