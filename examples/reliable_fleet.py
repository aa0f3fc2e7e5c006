"""Two robots publish a sensor topic through a router; one CEDDP-style wildcard reader gets both.

Shows the API the robot agent and the CEDDP use: ``Writer.write``, ``Writer.assert_unchanged``
for readings the local cache holds back, one ``Reader`` on ``arpz/{fleet}/robot/*/sensor/*``,
the events and the counters. Runs in about two seconds:

    python examples/reliable_fleet.py
"""

from __future__ import annotations

import threading
import time

from arpz.channel import (
    DataInfo,
    HistoryPolicy,
    QosProfile,
    Reader,
    ReaderEventCallbacks,
    Writer,
)
from arpz.core.transport import SessionSettings
from arpz.perf.harness import free_port
from arpz.transport.zenoh import ZenohTransport

QOS = QosProfile(history=HistoryPolicy.KEEP_ALL, deadline_s=0.5)


def main() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got: dict[str, list[int]] = {}
    lock = threading.Lock()

    def on_data(payload: bytes, info: DataInfo) -> None:
        with lock:
            got.setdefault(info.key, []).append(info.seq)

    events = ReaderEventCallbacks(
        matched=lambda s: print(f"matched: {s.current_count} writer(s)"),
        deadline=lambda s: print(f"deadline missed by {s.writer}: {s.total_count}"),
    )
    with (
        ZenohTransport.open(SessionSettings(mode="router", listen=[endpoint])),
        ZenohTransport.open(SessionSettings(connect=[endpoint]), timeout_s=5) as ceddp,
        ZenohTransport.open(SessionSettings(connect=[endpoint]), timeout_s=5) as robot1,
        ZenohTransport.open(SessionSettings(connect=[endpoint]), timeout_s=5) as robot2,
        Writer(robot1, "arpz/demo/robot/r1/sensor/dht11", QOS) as w1,
        Writer(robot2, "arpz/demo/robot/r2/sensor/dht11", QOS) as w2,
        Reader(ceddp, "arpz/demo/robot/*/sensor/*", QOS, on_data, events=events) as reader,
    ):
        deadline = time.monotonic() + 5
        while not (w1.matched_count and w2.matched_count) and time.monotonic() < deadline:
            time.sleep(0.005)  # a VOLATILE reader only gets what is written after the match
        last = None
        # 50 Hz for 2 s. Robot 2's reading changes every 0.8 s, longer than the 0.5 s deadline:
        # assert_unchanged keeps the topic alive at the reader without sending the value again.
        for i in range(100):
            w1.write(b"%d" % i)
            value = b"%d" % (i // 40)
            if value != last:
                w2.write(value)
                last = value
            else:
                w2.assert_unchanged()  # held back by the local cache: alive, no deadline miss
            time.sleep(0.02)
        for w in (w1, w2):
            w.wait_for_acknowledgments(2.0)
        time.sleep(0.1)
        with lock:
            for key, seqs in sorted(got.items()):
                print(f"{key}: {len(seqs)} samples, in order: {seqs == sorted(seqs)}")
        print("reader:", reader.stats())
        print("robot 2 writer:", w2.stats())


if __name__ == "__main__":
    main()
