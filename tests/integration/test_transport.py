import threading

import pytest

from arpz.core.errors import ArpzError
from arpz.core.transport import SessionSettings, TransportError
from arpz.transport.zenoh import ZenohTransport
from tests.support import client, free_port, router, wait_until

pytestmark = pytest.mark.integration


def test_put_subscribe_and_liveliness_through_a_real_router() -> None:
    with router() as (_, endpoint), client(endpoint) as a, client(endpoint) as b:
        got: list[tuple[str, bytes, bytes | None]] = []
        alive: list[tuple[str, bool]] = []
        b.subscribe("t/**", lambda k, p, att: got.append((k, p, att)))
        b.watch_liveliness("p/*", lambda k, up: alive.append((k, up)))
        token = a.declare_token("p/a")
        wait_until(lambda: ("p/a", True) in alive, what="token seen")
        pub = a.publisher("t/x")
        wait_until(lambda: (pub.put(b"1", attachment=b"h"), bool(got))[1], what="sample")
        assert got[0] == ("t/x", b"1", b"h")
        token.undeclare()
        wait_until(lambda: ("p/a", False) in alive, what="token gone")


def test_a_publisher_sees_a_subscriber_on_another_router_of_the_mesh() -> None:
    """What the robot agent waits for before its first reading: the route through the mesh."""
    with router() as (east, east_endpoint):
        west_endpoint = f"tcp/127.0.0.1:{free_port()}"
        west = ZenohTransport.open(
            SessionSettings(mode="router", listen=[west_endpoint], connect=[east_endpoint])
        )
        try:
            with client(west_endpoint) as robot:
                publisher = robot.publisher("arpz/mesh/robot/e2/sensor/pir")
                assert not publisher.matching
                handle = east.subscribe("arpz/mesh/robot/e$*/sensor/*", lambda k, p, a: None)
                wait_until(lambda: publisher.matching, what="east's subscriber seen from west")
                handle.undeclare()
                wait_until(lambda: not publisher.matching, what="east's subscriber gone")
        finally:
            west.close()


def test_undeclaring_a_pull_subscriber_ends_a_recv_blocked_in_another_thread() -> None:
    """What a reader's delivery thread relies on to stop: no wake-up sample is needed."""
    with router() as (_, endpoint), client(endpoint) as a, client(endpoint) as b:
        pull = b.subscribe_pull("t/pull", 10)
        got: list[object] = []

        def receive() -> None:
            try:
                while True:
                    got.append(pull.recv())
            except Exception as exc:  # the closed channel
                got.append(exc)

        thread = threading.Thread(target=receive, daemon=True)
        thread.start()
        pub = a.publisher("t/pull")
        wait_until(lambda: (pub.put(b"1"), bool(got))[1], what="a sample")
        assert got[0] == ("t/pull", b"1", None)
        pull.undeclare()
        thread.join(2.0)
        assert not thread.is_alive()
        assert isinstance(got[-1], Exception)


def test_zenoh_errors_come_out_of_the_seam_as_transport_errors() -> None:
    """Callers catch ``TransportError`` (an ``ArpzError``), never ``zenoh.ZError`` or
    ``Exception``: each call that Zenoh refuses says what was being done."""
    with router() as (_, endpoint), client(endpoint) as a:
        for call, what in [
            (lambda: a.put("bad//key", b"x"), "put on bad//key"),
            (lambda: a.publisher("bad//key"), "declare a publisher on bad//key"),
            (lambda: a.subscribe("bad//key", lambda k, p, att: None), "subscribe to bad//key"),
            (lambda: a.declare_token("bad//key"), "liveliness token bad//key"),
        ]:
            with pytest.raises(TransportError, match=what) as caught:
                call()
            assert isinstance(caught.value, ArpzError)
            assert type(caught.value.__cause__).__module__.startswith("zenoh"), caught.value


def wait_until_served(robot: ZenohTransport, key: str) -> None:
    """A queryable's declaration reaches the client through the router some time after
    ``serve`` returns; a request before that has nobody to answer it (a red CI, stop 32)."""
    answered: list[bytes] = []

    def asked_and_answered() -> bool:
        robot.request(key, b"?", answered.append, timeout_s=0.5)
        return wait_until(lambda: bool(answered), timeout_s=0.6, raise_on_timeout=False)

    wait_until(asked_and_answered, timeout_s=10.0, what=f"a reply from {key}'s queryable")


def test_a_request_starts_no_thread_and_its_replies_arrive(monkeypatch: pytest.MonkeyPatch) -> None:
    """zenoh-python starts a Python thread per request for a callable reply handler, and ``get``
    waits until it holds the GIL (benchmarks/investigations/request_cost.py); arpz's replies run
    on Zenoh's network thread, so a robot's clock bursts start none."""
    started: list[str] = []
    original_start = threading.Thread.start

    def counting_start(self: threading.Thread) -> None:
        started.append(self.name)
        original_start(self)

    with router() as (server, endpoint), client(endpoint) as robot:
        server.serve("clock/q", lambda payload: payload + b"!")
        wait_until_served(robot, "clock/q")
        replies: list[bytes] = []
        monkeypatch.setattr(threading.Thread, "start", counting_start)
        for i in range(10):
            # one at a time: a request is express and DROP (a lost clock exchange costs
            # nothing), and ten sent back to back on a loaded host lost some in 3 of 6 CIs
            robot.request("clock/q", str(i).encode(), replies.append, timeout_s=5.0)
            wait_until(lambda i=i: len(replies) == i + 1, what=f"reply {i}")
        monkeypatch.setattr(threading.Thread, "start", original_start)
    assert sorted(replies) == sorted(f"{i}!".encode() for i in range(10))
    assert started == [], started


def test_a_reply_handler_that_raises_is_logged_and_later_requests_still_get_replies(
    caplog: pytest.LogCaptureFixture,
) -> None:
    def broken(_payload: bytes) -> None:
        raise ValueError("a bad reply")

    with router() as (server, endpoint), client(endpoint) as robot:
        server.serve("clock/q", lambda payload: payload)
        wait_until_served(robot, "clock/q")
        robot.request("clock/q", b"1", broken, timeout_s=5.0)
        wait_until(lambda: "reply handler for clock/q raised" in caplog.text, what="the log")
        replies: list[bytes] = []
        robot.request("clock/q", b"2", replies.append, timeout_s=5.0)
        wait_until(lambda: replies == [b"2"], what="the next reply")
