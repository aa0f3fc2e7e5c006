"""Shared pytest wiring: the repository on sys.path, and callback assertions that fail the test.

The reliable channel catches whatever a user's callback raises (``on_data``, an event
callback), counts it in ``callback_errors`` and logs it on the ``arpz.channel`` logger, so
that one bad callback cannot stop the channel. In a test that is the wrong trade: an ``assert``
inside ``on_data`` that fails would be swallowed, and the test would go on to time out waiting
for something that never comes, hiding the real message. The autouse fixture below listens on
that logger and fails the test with the original AssertionError and its traceback: as the
test's own failure when the assert fails while the test runs, as a teardown error when it fails
later (while fixtures close the channel).
"""

from __future__ import annotations

import contextlib
import enum
import fcntl
import logging
import os
import sys
import tempfile
import traceback
import uuid
from collections.abc import Generator, Iterator
from pathlib import Path

import pytest
from hypothesis import settings

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

# Property tests check properties, not speed: hypothesis's default 200 ms deadline per example
# failed a CDR round trip of a camera frame while two grids loaded this shared 2-core host
# (17 s for a file that takes 3 s). Speed is the benchmarks' business (benchmarks/).
settings.register_profile("arpz", deadline=None)
settings.load_profile("arpz")

pytest_plugins = ["pytester"]

#: the logger the reliable channel reports a raising callback on (arpz/channel/_channel.py)
CHANNEL_LOGGER = "arpz.channel"
EXPECTED_MARKER = "callback_errors_expected"
#: the marker of a test that needs the machine's cores to itself (see ``cpu_share``)
CPU_EXCLUSIVE_MARKER = "cpu_exclusive"
#: the marker of an integration test that mostly waits (dead zones): it runs beside the
#: ``cpu_exclusive`` ones, as a unit test does (see ``share_of``)
MOSTLY_IDLE_MARKER = "mostly_idle"


def pytest_configure(config: pytest.Config) -> None:
    """Register the markers next to the code that reads them."""
    config.addinivalue_line(
        "markers",
        f"{CPU_EXCLUSIVE_MARKER}(whole_machine=False): a heavy or timing-bound test that runs "
        "with no integration test beside it (whole_machine: no test at all)",
    )
    config.addinivalue_line(
        "markers",
        f"{MOSTLY_IDLE_MARKER}: an integration test that spends most of its time waiting (a "
        "dead zone, a lease): it may run beside a cpu_exclusive test, as a unit test does",
    )
    config.addinivalue_line(
        "markers",
        f"{EXPECTED_MARKER}: the test makes a channel callback fail an assert on purpose; "
        "the callback-assertion check collects the failures but does not fail the test",
    )
    if _is_xdist_controller(config) and config.getoption("testrunuid", None) is None:
        # chosen here rather than by xdist, so the controller knows whose lock files to remove
        config.option.testrunuid = uuid.uuid4().hex


def _is_xdist_controller(config: pytest.Config) -> bool:
    return config.pluginmanager.hasplugin("xdist") and not hasattr(config, "workerinput")


def pytest_unconfigure(config: pytest.Config) -> None:
    """The controller removes the run's lock files (``cpu_share``): every worker has ended, so
    nothing holds them; the runs before this one left one set each in the temp folder."""
    run_id = config.getoption("testrunuid", None) if _is_xdist_controller(config) else None
    if run_id:
        for path in Path(tempfile.gettempdir()).glob(f"arpz-pytest-{run_id}-*"):
            path.unlink(missing_ok=True)


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


class Share(enum.IntEnum):
    """What a test holds of the machine while it runs; the value orders the suite."""

    #: the whole machine: no other test at all (``cpu_exclusive(whole_machine=True)``)
    MACHINE = 0
    #: no integration test beside it; unit tests may run (``cpu_exclusive``)
    CORES = 1
    #: a unit test: one process, beside anything but a MACHINE test
    UNIT = 2
    #: an integration test that mostly waits (``mostly_idle``): beside anything but a MACHINE
    #: test, as a unit test; after the unit tests, so that the worker beside the CORES tests
    #: takes it once its unit tests are done
    IDLE = 3
    #: an integration test: beside unit and integration tests
    SHARED = 4


def share_of(item: pytest.Item) -> Share:
    mark = item.get_closest_marker(CPU_EXCLUSIVE_MARKER)
    if mark is not None:
        return Share.MACHINE if mark.kwargs.get("whole_machine") else Share.CORES
    if item.get_closest_marker(MOSTLY_IDLE_MARKER) is not None:
        # The suite's serial part (the cpu_exclusive tests, 600 s) left the other worker idle
        # once the unit tests (100 s) were done, while the dead-zone tests (220 s, mostly
        # sleeping) waited for the end. Their bounds held at a load average of 10-16.
        return Share.IDLE
    if item.get_closest_marker("integration") is not None:
        return Share.SHARED
    return Share.UNIT


@contextlib.contextmanager
def _rw_lock(folder: Path, name: str, exclusive: bool) -> Iterator[None]:
    """A reader-writer lock of the test workers (two ``flock`` files). The turnstile makes a
    waiting writer block new readers, so it cannot be starved."""
    with (
        open(folder / f"{name}.turnstile", "a") as turnstile,
        open(folder / f"{name}.lock", "a") as lock,
    ):
        mode = fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH
        fcntl.flock(turnstile, mode)
        fcntl.flock(lock, mode)
        if not exclusive:
            fcntl.flock(turnstile, fcntl.LOCK_UN)  # let the next reader or writer queue
        yield  # closing the files at the end of the with releases what is still held


@contextlib.contextmanager
def cpu_share(share: Share) -> Iterator[None]:
    """Hold this test's share of the machine.

    The suite runs in two pytest-xdist workers on a 2-core machine. A heavy or timing-bound
    integration test (a fleet of robot processes, an overload, a latency bound) failed in CI
    whenever the other worker ran an integration test beside it (routers, robots, floods: more
    processes than cores), a different one each run. So the workers share two reader-writer
    locks: "integration" (integration tests read, ``cpu_exclusive`` ones write) and "machine"
    (unit tests read, ``whole_machine`` ones write). A unit test is one process, so the other
    worker runs the unit tests while the exclusive ones run (``pytest_collection_modifyitems``),
    except beside the ``whole_machine`` ones, whose bounds failed even with a unit test beside
    them (the quick experiment at 1 kHz lost samples). Without xdist there is nobody to share
    with."""
    run_id = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run_id is None:
        yield
        return
    folder = Path(tempfile.gettempdir())
    with contextlib.ExitStack() as held:
        if share in (Share.MACHINE, Share.UNIT, Share.IDLE):
            held.enter_context(
                _rw_lock(folder, f"arpz-pytest-{run_id}-machine", share is Share.MACHINE)
            )
        if share in (Share.MACHINE, Share.CORES, Share.SHARED):
            held.enter_context(
                _rw_lock(folder, f"arpz-pytest-{run_id}-integration", share is not Share.SHARED)
            )
        yield


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_protocol(item: pytest.Item) -> Generator[None, object, object]:
    """Run each test, setup to teardown, inside its share of the machine.

    ``tryfirst`` makes this the outermost wrapper, so the time a test waits for its share is not
    counted by pytest-timeout, whose timer starts inside it."""
    with cpu_share(share_of(item)):
        return (yield)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Order the suite so that the exclusive tests overlap the unit tests, not idle time.

    xdist's ``load`` scheduling first hands each worker a chunk of consecutive tests (an eighth
    of the suite each), then more in collection order as they finish. With the exclusive tests
    first, one worker's chunk starts with all of them and the other worker's is unit tests, which
    it keeps taking while the exclusive ones run, then the integration tests that mostly wait
    (``mostly_idle``), which may run beside the exclusive ones too; the other integration tests
    come last. (Not
    ``--dist loadgroup``: with pytest 9, pytest-xdist 3.8 sets its group suffix on a node id
    attribute pytest no longer reads, so ``xdist_group`` is silently ignored.)"""
    items.sort(key=share_of)  # stable: files keep their order
