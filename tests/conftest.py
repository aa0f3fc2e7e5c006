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

import logging
import sys
import traceback
from collections.abc import Generator, Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

pytest_plugins = ["pytester"]

#: the logger the reliable channel reports a raising callback on (arpz/reliability/_channel.py)
CHANNEL_LOGGER = "arpz.reliability"
EXPECTED_MARKER = "callback_errors_expected"


def pytest_configure(config: pytest.Config) -> None:
    """Register the marker next to the fixture that reads it."""
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


#: timing-bound tests of the "fleet_cpu" group that run last in it: the group's worker starts
#: them after the other worker has run the rest of the suite (abuse floods, camera frames),
#: which held the lost-change test over its 100 ms bound when it ran first (4 CI runs of 5)
_LAST_IN_GROUP = ("test_a_lost_change_does_not_leave_the_ceddp_on_a_stale_value",)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    last = [item for item in items if item.name in _LAST_IN_GROUP]
    items[:] = [item for item in items if item.name not in _LAST_IN_GROUP] + last
