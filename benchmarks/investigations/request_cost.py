"""What a Zenoh request costs the thread that sends it: zenoh-python's default reply handler
against arpz's ``ZenohTransport.request``, in one run.

A robot's clock synchronisation sends a burst of 4 requests every 2 s from its sensing loop.
Given a Python callable, zenoh-python starts a Python thread for every request to run the reply
callback on, and ``get`` returns only once that thread holds the GIL: a stall of the sensing
loop that grows with the threads competing for the GIL (a fleet worker packing 13 robots has
about 770). arpz runs the reply callback on Zenoh's network thread instead (``indirect=False``).

A router session with a queryable that echoes and a client session live in this process; each
request is followed by a 2 ms pause (a sensing loop does not send back to back). ``--threads N``
adds N Python threads that each wake every 10 ms and do a little work, as a fleet worker's
channel threads do. Prints, per variant, the caller's time in the request call, the process's
CPU a request and the replies received; the ratio is arpz / zenoh-python. Alternating rounds,
median of the rounds.

    python benchmarks/investigations/request_cost.py [--requests 400] [--rounds 3] [--threads 0]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from arpz.core.transport import SessionSettings  # noqa: E402
from arpz.tools.launch import free_port  # noqa: E402
from arpz.transport.zenoh import ZenohTransport  # noqa: E402

KEY = "bench/request"


def background(count: int, stop: threading.Event) -> list[threading.Thread]:
    def wake() -> None:
        while not stop.wait(0.01):
            sum(range(50))

    threads = [threading.Thread(target=wake, daemon=True) for _ in range(count)]
    for thread in threads:
        thread.start()
    return threads


def measure(
    send: Callable[[Callable[[bytes], None]], None], requests: int
) -> tuple[float, float, int]:
    """(caller's us in the call, process CPU us, replies) a request."""
    replies = [0]
    lock = threading.Lock()

    def on_reply(_payload: bytes) -> None:
        with lock:
            replies[0] += 1

    in_call = 0.0
    cpu0 = time.process_time()
    for _ in range(requests):
        start = time.perf_counter()
        send(on_reply)
        in_call += time.perf_counter() - start
        time.sleep(0.002)
    deadline = time.monotonic() + 10
    while replies[0] < requests and time.monotonic() < deadline:
        time.sleep(0.01)
    cpu_s = time.process_time() - cpu0
    return in_call / requests * 1e6, cpu_s / requests * 1e6, replies[0]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--requests", type=int, default=400)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="busy Python threads beside")
    args = ap.parse_args()
    if args.requests < 1 or args.rounds < 1 or args.threads < 0:
        ap.error("--requests and --rounds must be >= 1, --threads >= 0")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = ZenohTransport.open(SessionSettings(mode="router", listen=[endpoint]))
    client = ZenohTransport.open(SessionSettings(mode="client", connect=[endpoint]))
    stop = threading.Event()
    try:
        server.serve(KEY, lambda payload: payload)
        session = client._session  # the same session, asked the way zenoh-python's docs do

        def raw(on_reply: Callable[[bytes], None]) -> None:
            def on_answer(reply: zenoh.Reply) -> None:
                if reply.ok is not None:
                    on_reply(reply.ok.payload.to_bytes())

            session.get(KEY, on_answer, payload=b"t" * 16, timeout=2.0)

        def arpz(on_reply: Callable[[bytes], None]) -> None:
            client.request(KEY, b"t" * 16, on_reply, timeout_s=2.0)

        background(args.threads, stop)
        rows: dict[str, list[tuple[float, float, int]]] = {"zenoh-python": [], "arpz": []}
        for index in range(args.rounds):
            for name, send in (("zenoh-python", raw), ("arpz", arpz)):
                rows[name].append(measure(send, args.requests))
                in_call, cpu, got = rows[name][-1]
                print(
                    f"round {index + 1}/{args.rounds} {name:13s} in call {in_call:7.0f} us, "
                    f"CPU {cpu:6.0f} us a request, replies {got}/{args.requests}",
                    flush=True,
                )
    finally:
        stop.set()
        client.close()
        server.close()
    medians = {
        name: (statistics.median(r[0] for r in rs), statistics.median(r[1] for r in rs))
        for name, rs in rows.items()
    }
    raw_call, raw_cpu = medians["zenoh-python"]
    arpz_call, arpz_cpu = medians["arpz"]
    print(
        f"\n{args.requests} requests a round, {args.threads} busy threads beside, median of "
        f"{args.rounds}:\n  zenoh-python default handler: {raw_call:7.0f} us in the call, "
        f"{raw_cpu:6.0f} us CPU\n  arpz ZenohTransport.request  : {arpz_call:7.0f} us in the "
        f"call ({arpz_call / raw_call:.2f}x), {arpz_cpu:6.0f} us CPU ({arpz_cpu / raw_cpu:.2f}x)"
    )
    missing = {name: sum(args.requests - r[2] for r in rs) for name, rs in rows.items()}
    if any(missing.values()):
        print(f"FAILED: replies missing (a figure a request is then not one): {missing}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
