"""A writer's session behind an emulated lossy UDP link, a reader's on clean TCP, one router.

writer -> arpz.netem proxy (loss after a clean start) -> router <- reader (TCP). Used by the
reliable channel's lossy tests and the large-message test; each names its own loss model and
session settings (shared memory off for large payloads, one radio frame per datagram).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass

from arpz.core.transport import SessionSettings
from arpz.netem.process import NetemProcess, netem_process
from arpz.transport.zenoh import ZenohTransport
from tests.support import free_port, free_udp_port

CLEAN_S = 1.5


@dataclass
class LossyLink:
    writer_side: ZenohTransport
    reader_side: ZenohTransport
    netem: NetemProcess
    #: monotonic time from which the link loses datagrams (at most)
    lossy_from: float


@contextmanager
def lossy_link(
    *netem_args: str,
    every_session: dict[str, object] | None = None,
    writer_session: dict[str, object] | None = None,
) -> Iterator[LossyLink]:
    """``netem_args``: the loss model (e.g. ``"--loss", "10", "--seed", "11"``), applied after
    CLEAN_S; ``every_session``: Zenoh settings of all three sessions; ``writer_session``: more
    for the writer's."""
    common = every_session or {}
    udp, tcp, proxy = free_udp_port(), free_port(), free_udp_port()
    with ExitStack() as stack:
        listen = [f"udp/127.0.0.1:{udp}", f"tcp/127.0.0.1:{tcp}"]
        stack.enter_context(
            ZenohTransport.open(SessionSettings(mode="router", listen=listen, extra=common))
        )
        netem = stack.enter_context(
            netem_process(
                f"udp/127.0.0.1:{proxy}",
                f"udp/127.0.0.1:{udp}",
                *netem_args,
                *("--clean-s", str(CLEAN_S)),
            )
        )
        # the proxy said "ready" after its clock started: loss is on from here + CLEAN_S at most
        lossy_from = time.monotonic() + CLEAN_S
        writer_extra = {**common, **(writer_session or {})}
        a = stack.enter_context(
            ZenohTransport.open(
                SessionSettings(connect=[f"udp/127.0.0.1:{proxy}"], extra=writer_extra),
                timeout_s=5,
            )
        )
        b = stack.enter_context(
            ZenohTransport.open(
                SessionSettings(connect=[f"tcp/127.0.0.1:{tcp}"], extra=common), timeout_s=5
            )
        )
        yield LossyLink(a, b, netem, lossy_from)
