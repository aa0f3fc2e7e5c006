"""The check in tests/conftest.py: an assert that fails inside a channel callback fails the test.

The channel catches what a callback raises and goes on (arpz/channel/_channel.py); without
the check such a test would end in a timeout instead of the assertion's own message.
"""

from __future__ import annotations

import pytest

from arpz.channel import (
    QOS_RELIABLE_ALL,
    DataInfo,
    MatchedStatus,
    Reader,
    ReaderEventCallbacks,
    Writer,
)
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.conftest import CallbackAssertions
from tests.support import wait_until


@pytest.mark.callback_errors_expected
def test_an_assert_failing_in_on_data_is_collected_with_its_message(
    callback_assertions: CallbackAssertions,
) -> None:
    bus = MemoryBus()

    def on_data(payload: bytes, info: DataInfo) -> None:
        assert payload == b"expected", f"on_data got {payload!r}"

    with (
        Reader(MemoryTransport(bus), "t", QOS_RELIABLE_ALL, on_data) as reader,
        Writer(MemoryTransport(bus), "t", QOS_RELIABLE_ALL) as writer,
    ):
        wait_until(lambda: writer.matched_count == 1, what="match")
        writer.write(b"other")
        wait_until(lambda: reader.stats().callback_errors == 1, what="the callback to raise")
    [record] = callback_assertions.records
    assert record.exc_info is not None
    assert isinstance(record.exc_info[1], AssertionError)
    assert "on_data got b'other'" in callback_assertions.report()
    assert "in on_data" in callback_assertions.report()  # the callback's own frame


@pytest.mark.callback_errors_expected
def test_an_assert_failing_in_an_event_callback_is_collected(
    callback_assertions: CallbackAssertions,
) -> None:
    bus = MemoryBus()

    def on_matched(status: MatchedStatus) -> None:
        assert status.current_count == 0, "matched event on purpose"

    with (
        Reader(
            MemoryTransport(bus),
            "t",
            QOS_RELIABLE_ALL,
            lambda p, i: None,
            events=ReaderEventCallbacks(matched=on_matched),
        ),
        Writer(MemoryTransport(bus), "t", QOS_RELIABLE_ALL),
    ):
        wait_until(lambda: bool(callback_assertions.records), what="the event callback to raise")
    assert "matched event on purpose" in callback_assertions.report()


def test_a_callback_raising_something_else_is_not_taken_for_a_failed_assert(
    callback_assertions: CallbackAssertions,
) -> None:
    """Tests that make a callback raise on purpose (to prove the channel goes on) stay green."""
    bus = MemoryBus()

    def on_data(payload: bytes, info: DataInfo) -> None:
        raise RuntimeError("on purpose")

    with (
        Reader(MemoryTransport(bus), "t", QOS_RELIABLE_ALL, on_data) as reader,
        Writer(MemoryTransport(bus), "t", QOS_RELIABLE_ALL) as writer,
    ):
        wait_until(lambda: writer.matched_count == 1, what="match")
        writer.write(b"x")
        wait_until(lambda: reader.stats().callback_errors == 1, what="the callback to raise")
    assert callback_assertions.records == []


_INNER_TEST = """
from arpz.transport.memory import MemoryBus, MemoryTransport
from arpz.channel import QOS_RELIABLE_ALL, Reader, Writer
from tests.support import wait_until

def test_inner():
    bus = MemoryBus()
    got = []

    def on_data(payload, info):
        assert payload == PAYLOAD_EXPECTED, "inner on_data assert"
        got.append(payload)

    with (
        Reader(MemoryTransport(bus), "t", QOS_RELIABLE_ALL, on_data),
        Writer(MemoryTransport(bus), "t", QOS_RELIABLE_ALL) as writer,
    ):
        wait_until(lambda: writer.matched_count == 1, what="match")
        writer.write(b"sent")
        wait_until(lambda: got, timeout_s=1.0, what="the sample")
"""


def _run_inner(pytester: pytest.Pytester, expected: bytes) -> pytest.RunResult:
    pytester.makeconftest(
        "from tests.conftest import callback_assertions, pytest_configure, pytest_runtest_call\n"
    )
    pytester.makepyfile(_INNER_TEST.replace("PAYLOAD_EXPECTED", repr(expected)))
    return pytester.runpytest_inprocess("-p", "no:cacheprovider")


# the inner run is in-process: its records reach this test's own check too, on purpose
@pytest.mark.callback_errors_expected
def test_an_unmarked_test_whose_callback_assert_fails_fails_with_the_original_message(
    pytester: pytest.Pytester,
) -> None:
    result = _run_inner(pytester, b"something else")
    # the test fails with the callback's assertion, not with the timeout it led to (which
    # stays in the report as the context)
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(
        [
            "*timed out after 1.0 s waiting for the sample*",
            "*During handling of the above exception, another exception occurred*",
            "*def on_data(payload, info):*",
            "E*AssertionError: inner on_data assert",
        ]
    )


@pytest.mark.callback_errors_expected
def test_an_unmarked_test_whose_callbacks_pass_passes(pytester: pytest.Pytester) -> None:
    result = _run_inner(pytester, b"sent")
    result.assert_outcomes(passed=1)
