"""Subscribe to one robot's sensor topics with plain zenoh-python, importing nothing from arpz.

Everything needed is in docs/protocol.md: the key ``arpz/{fleet}/robot/{robot}/sensor/{topic}``
and the payload, a msgpack array ``[writer, seq, stamp_ns, value]``.

    python examples/raw_subscriber.py --connect tcp/127.0.0.1:7447 --fleet demo --robot robot1
"""

from __future__ import annotations

import argparse
import json
import threading
import time

import msgspec  # used as a plain msgpack decoder; any msgpack library works
import zenoh


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--connect", required=True)
    parser.add_argument("--fleet", default="default")
    parser.add_argument("--robot", required=True)
    parser.add_argument("--count", type=int, default=20, help="stop after this many samples")
    parser.add_argument("--timeout", type=float, default=20.0)
    args = parser.parse_args()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    received: list[dict[str, object]] = []
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        # by position: later versions may append elements (changed_ns is the fifth)
        writer, seq, stamp_ns, value = msgspec.msgpack.decode(sample.payload.to_bytes())[:4]
        topic = str(sample.key_expr).rsplit("/", 1)[-1]
        received.append(
            {
                "topic": topic,
                "writer": writer,
                "seq": seq,
                "stamp_ns": stamp_ns,
                "value": value,
                "type": type(value).__name__,
            }
        )
        if len(received) >= args.count:
            done.set()

    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(
            f"arpz/{args.fleet}/robot/{args.robot}/sensor/*", on_sample
        )
        done.wait(args.timeout)
        sub.undeclare()
    for row in received[: args.count]:
        print(json.dumps(row))
    time.sleep(0)
    return 0 if len(received) >= args.count else 1


if __name__ == "__main__":
    raise SystemExit(main())
