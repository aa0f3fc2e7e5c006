"""``ZenohTransport``'s deferred queries (``arpz.core.transport.DeferredQueries``) through a real
router: a reply sent later from another thread, every reply handed on as it comes, the end
told once (at the last finish, at the timeout, or at once with nobody serving), and a queryable
that survives a reopen of the session."""

from __future__ import annotations

import threading
import time

import pytest

from arpz.core.transport import DeferredQueries, Responder, SessionSettings
from arpz.transport.zenoh import ZenohTransport
from tests.support import router, wait_until

pytestmark = pytest.mark.integration


class Asker:
    """One query's replies and end, as the transport hands them over."""

    def __init__(self) -> None:
        self.replies: list[tuple[float, bytes]] = []
        self.ends: list[float] = []
        self.done = threading.Event()
        self.started = time.monotonic()

    def on_reply(self, payload: bytes) -> None:
        self.replies.append((time.monotonic() - self.started, payload))

    def on_done(self) -> None:
        self.ends.append(time.monotonic() - self.started)
        self.done.set()


def client(endpoint: str) -> ZenohTransport:
    return ZenohTransport.open(SessionSettings(mode="client", connect=[endpoint]), timeout_s=5)


def test_a_deferred_reply_comes_later_from_another_thread_and_the_end_is_told_once() -> None:
    held: list[Responder] = []

    def serve(key: str, payload: bytes, responder: Responder) -> None:
        responder.reply(b"accepted " + key.rsplit("/", 1)[-1].encode())
        if payload == b"hang":
            held.append(responder)
            return

        def later() -> None:
            time.sleep(0.2)
            responder.reply(b"answer to " + payload)
            responder.finish()
            responder.finish()  # idempotent
            assert not responder.reply(b"after the finish")

        threading.Thread(target=later).start()

    with router() as (_router, endpoint):
        server, asking = client(endpoint), client(endpoint)
        try:
            assert isinstance(server, DeferredQueries)
            server.serve_deferred("q/srv/*", serve)
            time.sleep(0.3)  # the queryable's declaration reaches the router
            answered = Asker()
            asking.query("q/srv/dock", b"x", answered.on_reply, answered.on_done, timeout_s=3)
            assert answered.done.wait(5)
            assert [p for _, p in answered.replies] == [b"accepted dock", b"answer to x"]
            assert answered.replies[0][0] < 0.15 <= answered.replies[1][0]
            hung = Asker()
            asking.query("q/srv/slow", b"hang", hung.on_reply, hung.on_done, timeout_s=0.5)
            assert hung.done.wait(5)
            assert [p for _, p in hung.replies] == [b"accepted slow"]
            assert 0.45 <= hung.ends[0] < 2.0, hung.ends
            held[0].reply(b"too late")  # sent: the requester drops it
            held[0].finish()
            nobody = Asker()
            asking.query("q/none/x", b"x", nobody.on_reply, nobody.on_done, timeout_s=3)
            assert nobody.done.wait(5) and nobody.ends[0] < 1.0 and not nobody.replies
            time.sleep(0.2)
            assert len(answered.ends) == len(hung.ends) == len(nobody.ends) == 1
            assert [p for _, p in hung.replies] == [b"accepted slow"], "the late reply dropped"
        finally:
            asking.close()
            server.close()


def test_a_deferred_queryable_is_declared_again_on_a_reopened_session() -> None:
    def serve(key: str, payload: bytes, responder: Responder) -> None:
        responder.reply(b"ok")
        responder.finish()

    with router() as (_router, endpoint):
        server, asking = client(endpoint), client(endpoint)
        try:
            server.serve_deferred("q/srv/*", serve)
            server.reopen()

            def answered() -> bool:
                asker = Asker()
                asking.query("q/srv/a", b"", asker.on_reply, asker.on_done, timeout_s=1)
                asker.done.wait(2)
                return [p for _, p in asker.replies] == [b"ok"]

            wait_until(answered, timeout_s=10, what="the queryable on the new session")
        finally:
            asking.close()
            server.close()
