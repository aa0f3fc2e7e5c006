"""``ZenohTransport.reopen`` through a real router on loopback (issue 39): a new session, and every
handle given out before keeps working; a robot's link defaults apply under a zenoh_config."""

from __future__ import annotations

import contextlib
import json
import socket
import struct
import threading
from pathlib import Path

import pytest

from arpz.core.transport import CLIENT_LINK_DEFAULTS, Received, SessionSettings, TransportError
from arpz.tools.launch import free_port
from arpz.transport.zenoh import ZenohTransport, _abort_on_close, build_config, config_value
from tests.support import router, wait_until

pytestmark = pytest.mark.integration


def _client(endpoint: str) -> ZenohTransport:
    settings = SessionSettings(mode="client", connect=[endpoint], defaults=CLIENT_LINK_DEFAULTS)
    return ZenohTransport.open(settings, timeout_s=5)


def test_every_handle_works_on_the_reopened_session() -> None:
    with router() as (ceddp, endpoint):
        robot = _client(endpoint)
        try:
            to_ceddp: list[bytes] = []
            to_robot: list[bytes] = []
            pulled: list[Received | str] = []
            alive: list[tuple[str, bool]] = []
            seen_by_ceddp: list[bool] = []
            answers: list[bytes] = []
            ceddp.subscribe("t/up", lambda _k, payload, _a: to_ceddp.append(payload))
            publisher = robot.publisher("t/up", block=False)
            robot.subscribe("t/down", lambda _k, payload, _a: to_robot.append(payload))
            pull = robot.subscribe_pull("t/pull", 16)

            def receive() -> None:
                while True:
                    try:
                        pulled.append(pull.recv())
                    except TransportError as exc:  # the end: undeclared by close()
                        pulled.append(str(exc))
                        return

            receiver = threading.Thread(target=receive, daemon=True)
            receiver.start()
            ceddp.declare_token("tok/ceddp")
            ceddp.declare_token("tok/ceddp2")
            robot.watch_liveliness("tok/**", lambda key, up: alive.append((key, up)))
            robot.declare_token("own/robot")
            ceddp.watch_liveliness("own/robot", lambda _k, up: seen_by_ceddp.append(up))
            robot.serve("q/robot", lambda payload: b"answer " + payload)
            wait_until(lambda: publisher.matching, what="the router's subscriber matched")

            def exchange(word: bytes) -> None:
                """Each way once, asked again until it came (a declaration reaches the router
                a moment after it is made, and what came before is not routed)."""

                def arrived() -> bool:
                    return (
                        word in to_ceddp
                        and word in to_robot
                        and any(p[1] == word for p in pulled if not isinstance(p, str))
                        and b"answer " + word in answers
                    )

                def send() -> bool:
                    publisher.put(word)
                    ceddp.put("t/down", word)
                    ceddp.put("t/pull", word)
                    ceddp.request("q/robot", word, answers.append, timeout_s=0.5)
                    return wait_until(arrived, timeout_s=0.5, raise_on_timeout=False)

                wait_until(send, what=f"{word!r} both ways")

            exchange(b"before")
            zid = robot.zid
            delivered = robot.delivered
            robot.reopen()
            assert robot.zid != zid and robot.reopens == 1 and not robot.down
            exchange(b"after")
            assert robot.delivered > delivered
            # the watcher saw both tokens alive again on the new session, and none vanish:
            # they never did
            assert sorted(alive[:2]) == [("tok/ceddp", True), ("tok/ceddp2", True)]
            wait_until(
                lambda: {key for key, _ in alive[2:]} == {"tok/ceddp", "tok/ceddp2"},
                what="the tokens alive again",
            )
            assert all(up for _, up in alive), alive
            assert seen_by_ceddp[0] is True and seen_by_ceddp[-1] is True
        finally:
            robot.close()
        receiver.join(5)
        assert not receiver.is_alive() and isinstance(pulled[-1], str)


def test_a_transport_that_cannot_reopen_stays_down_and_drops_what_it_is_given() -> None:
    with router() as (ceddp, endpoint):
        robot = _client(endpoint)
        try:
            got: list[bytes] = []
            alive: list[tuple[str, bool]] = []
            ceddp.subscribe("t/up", lambda _k, payload, _a: got.append(payload))
            publisher = robot.publisher("t/up", block=False)
            old_reader = ceddp.declare_token("tok/reader-1")
            ceddp.declare_token("tok/reader-2")
            robot.watch_liveliness("tok/*", lambda key, up: alive.append((key, up)))
            wait_until(lambda: publisher.matching and len(alive) == 2, what="a match, tokens")
            # the router's endpoint is gone: reopening fails, and the transport is down
            robot.settings = SessionSettings(
                mode="client",
                connect=[f"tcp/127.0.0.1:{free_port()}"],
                defaults=CLIENT_LINK_DEFAULTS,
            )
            with pytest.raises(TransportError, match="cannot open a Zenoh client session"):
                robot.reopen()
            assert robot.down
            publisher.put(b"dropped")  # no error: dropped, as on a congested link
            robot.put("t/up", b"dropped too")
            robot.request("q/x", b"", lambda _p: None, timeout_s=0.1)
            late = robot.subscribe("t/late", lambda _k, payload, _a: got.append(payload))
            old_reader.undeclare()  # gone while the robot was away: it must hear so
            ceddp.declare_token("tok/reader-3")
            robot.settings = SessionSettings(
                mode="client", connect=[endpoint], defaults=CLIENT_LINK_DEFAULTS
            )
            robot.reopen()
            assert not robot.down and robot.reopens == 1
            assert ("tok/reader-1", False) in alive  # said by the reopen itself
            wait_until(lambda: ("tok/reader-3", True) in alive, what="the new token")
            assert ("tok/reader-2", False) not in alive  # alive throughout: never vanished
            publisher.put(b"back")
            wait_until(lambda: got == [b"back"], what="a put on the new session")

            def late_arrived() -> bool:
                """The router learns the late subscriber a moment after the reopen: ask again
                until it has."""
                ceddp.put("t/late", b"declared while down")
                return wait_until(
                    lambda: len(got) > 1, timeout_s=0.2, what="", raise_on_timeout=False
                )

            wait_until(late_arrived, what="the subscriber declared while down")
            assert got[1] == b"declared while down"
            late.undeclare()
        finally:
            robot.close()
        with pytest.raises(TransportError):
            robot.reopen()


def test_link_defaults_apply_where_the_zenoh_config_is_silent(tmp_path: Path) -> None:
    own = tmp_path / "robot.json5"
    own.write_text(json.dumps({"transport": {"unicast": {"open_timeout": 4000}}}))
    settings = SessionSettings(mode="client", config_file=str(own), defaults=CLIENT_LINK_DEFAULTS)
    conf = build_config(settings)
    assert config_value(conf, "transport/unicast/open_timeout") == 4000  # the file's
    assert config_value(conf, "connect/retry") == {
        "period_init_ms": 250,
        "period_max_ms": 500,
        "period_increase_factor": 2.0,
    }
    plain = build_config(SessionSettings(mode="client"))
    assert config_value(plain, "transport/unicast/open_timeout") == 10000  # Zenoh's own


def test_the_old_sessions_connections_are_found_and_set_to_close_by_reset() -> None:
    """``_abort_on_close`` finds a TCP connection of this process by its addresses, beside unix
    sockets it must skip, and sets SO_LINGER {on, 0} on it (its close is then a reset)."""
    with contextlib.ExitStack() as stack:
        server = stack.enter_context(socket.create_server(("127.0.0.1", 0)))
        client = stack.enter_context(socket.create_connection(server.getsockname()))
        accepted = stack.enter_context(server.accept()[0])
        for unix in socket.socketpair():
            stack.enter_context(unix)
        pair = (client.getsockname()[:2], client.getpeername()[:2])
        assert _abort_on_close({pair}) == 1
        linger = client.getsockopt(socket.SOL_SOCKET, socket.SO_LINGER, 8)
        assert struct.unpack("ii", linger) == (1, 0)
        assert accepted.getsockopt(socket.SOL_SOCKET, socket.SO_LINGER, 8) == bytes(8)
        assert _abort_on_close(set()) == 0
