import pytest

from tests.support import client, router, wait_until

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
