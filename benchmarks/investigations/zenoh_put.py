"""What one put costs on the calling thread: ``ZenohTransport.put`` (the channel's ACKNACKs,
heartbeats and resends), raw ``Session.put`` on the same keys, and a declared publisher's put.

A CEDDP puts on about two keys per matched writer, again and again. A publisher kept per key
was tried and not kept (README.md here, stop 27): this prints what it would save. Two
sessions in this process, a peer listening on loopback and a client with a subscriber on the
other side, so every put leaves the process.

    python benchmarks/investigations/zenoh_put.py [--keys 400] [--puts 20000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from arpz.core.transport import SessionSettings
from arpz.transport.zenoh import ZenohTransport
from tests.support import free_port, wait_until


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--keys", type=int, default=400)
    ap.add_argument("--puts", type=int, default=20_000)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    received = [0]
    with zenoh.open(conf) as listener:
        subscriber = listener.declare_subscriber(
            "f/**", lambda _: received.__setitem__(0, received[0] + 1)
        )
        ours = ZenohTransport.open(SessionSettings(mode="client", connect=[endpoint]), timeout_s=5)
        try:
            raw = ours._session
            keys = [
                f"f/robot/r{i // 8}/sensor/s{i % 8}/rel/an/0a1b2c3d/4e5f6a7b"
                for i in range(args.keys)
            ]
            wait_until(lambda: (raw.put(keys[0], b"probe"), received[0] > 0)[1], what="route")
            publishers = [raw.declare_publisher(key) for key in keys]
            payload = b"x" * 40
            n = args.keys

            def timed(put: Callable[[int], object]) -> float:
                start = time.perf_counter()
                for i in range(args.puts):
                    put(i)
                return (time.perf_counter() - start) / args.puts * 1e6

            paths: dict[str, Callable[[int], object]] = {
                "arpz ZenohTransport.put": lambda i: ours.put(keys[i % n], payload),
                "raw Session.put": lambda i: raw.put(keys[i % n], payload),
                "declared publisher put": lambda i: publishers[i % n].put(payload),
            }
            results: dict[str, list[float]] = {name: [] for name in paths}
            for round_ in range(1, args.rounds + 1):
                for name, put in paths.items():
                    results[name].append(timed(put))
                print(f"round {round_}/{args.rounds} done", file=sys.stderr)
            for publisher in publishers:
                publisher.undeclare()
        finally:
            ours.close()
            subscriber.undeclare()
    base = statistics.median(results["raw Session.put"])
    print(f"{args.puts} puts of 40 B over {args.keys} keys, median of {args.rounds}:")
    for name, values in results.items():
        us = statistics.median(values)
        print(f"  {name:<24}: {us:6.1f} us a put ({us / base:.2f}x raw Session.put)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
