"""Live QoS control through a real router: a fourth robot joins a running fleet and leaves."""

from __future__ import annotations

import threading
import time
from contextlib import ExitStack
from pathlib import Path

import pytest

from arpz.channel import Reader
from arpz.core.messages import (
    QOS_ACK_DECODER,
    QOS_ASSIGNMENT_DECODER,
    STATS_DECODER,
    QosAck,
    QosAssignmentMsg,
    RobotStats,
)
from arpz.core.protocol.events import DataInfo
from arpz.core.traffic import ASSIGNMENT_QOS, REPORT_QOS
from arpz.core.transport import Transport
from tests.integration.fleet import Process, ceddp, robots, write_robot
from tests.support import client, wait_until

pytestmark = pytest.mark.integration


class Watcher:
    """A client recording assignments, acknowledgements and robot stats as they pass, through
    reliable-channel readers of the keys (``attach``): a message larger than its writer's link
    fragment (a CEDDP that also listens on UDP cuts at 1 280 bytes) arrives as fragments, which
    only a reader puts back together."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.assignments: list[QosAssignmentMsg] = []
        self.acks: list[QosAck] = []
        self.stats: dict[str, RobotStats] = {}

    def attach(self, transport: Transport, stack: ExitStack, fleet: str = "itest") -> None:
        """Readers of the CEDDP's assignments and the robots' reports, closed with ``stack``."""
        readers = [
            Reader(transport, f"arpz/{fleet}/ceddp/qos", ASSIGNMENT_QOS, self._assignment),
            *(
                Reader(transport, f"arpz/{fleet}/robot/*/{kind}", REPORT_QOS, self._report)
                for kind in ("qos", "stats", "announce")
            ),
        ]
        for reader in readers:
            stack.callback(reader.close)

    def _assignment(self, payload: bytes, info: DataInfo) -> None:
        self.on_assignment(info.key, payload, None)

    def _report(self, payload: bytes, info: DataInfo) -> None:
        self.on_robot(info.key, payload, None)

    def on_assignment(self, key: str, payload: bytes, att: bytes | None) -> None:
        with self.lock:
            self.assignments.append(QOS_ASSIGNMENT_DECODER.decode(payload))

    def on_robot(self, key: str, payload: bytes, att: bytes | None) -> None:
        kind = key.rsplit("/", 1)[-1]
        with self.lock:
            if kind == "qos":
                self.acks.append(QOS_ACK_DECODER.decode(payload))
            elif kind == "stats":
                stats = STATS_DECODER.decode(payload)
                self.stats[stats.robot] = stats

    def latest(self, robots: set[str]) -> QosAssignmentMsg | None:
        with self.lock:
            for message in reversed(self.assignments):
                if set(message.robots) == robots:
                    return message
        return None

    def acked(self, epoch: int, robots: set[str]) -> dict[str, QosAck]:
        with self.lock:
            got = {a.robot: a for a in self.acks if a.epoch == epoch and a.status == "applied"}
        return got if set(got) >= robots else {}


def test_a_fourth_robot_joins_and_leaves(tmp_path: Path) -> None:
    three = {"robot1", "robot2", "robot3"}
    four = three | {"robot4"}
    watcher = Watcher()
    qos = "[qos]\nenabled = true\nrmax_hz = 100.0\n"
    with (
        ceddp(tmp_path, extra=qos) as (_server, endpoint),
        client(endpoint) as raw,
        ExitStack() as readers,
    ):
        watcher.attach(raw, readers)
        configs = [
            write_robot(tmp_path, "robot1", endpoint, preset="machine1"),
            write_robot(tmp_path, "robot2", endpoint, preset="machine2"),
            write_robot(tmp_path, "robot3", endpoint, preset="machine3"),
        ]
        with robots(tmp_path, configs):
            wait_until(lambda: watcher.latest(three) is not None, what="QoS for 3 robots")
            before = watcher.latest(three)
            assert before is not None
            # eq. 1 topic counts 7, 6, 6: R = 300/19 - 1 Hz, D = 738 (hand-computed)
            assert before.robots["robot1"].rate_hz == pytest.approx(300 / 19 - 1)
            assert before.robots["robot1"].depth == 738
            wait_until(lambda: bool(watcher.acked(before.epoch, three)), what="3 acks")
            # the robots really run at R now (they were configured at 50 Hz)
            wait_until(
                lambda: (
                    "robot1" in watcher.stats
                    and all(
                        abs(t.produced_rate_hz - before.robots["robot1"].rate_hz) < 4
                        for t in watcher.stats["robot1"].topics.values()
                    )
                ),
                timeout_s=5,
                what="robot1 sensing at R",
            )

            fourth = Process(
                "robot4",
                [
                    "-m",
                    "arpz.robot",
                    "--config",
                    str(write_robot(tmp_path, "robot4", endpoint, preset="machine2")),
                ],
                tmp_path,
            )
            try:
                fourth.wait_for("running")
                wait_until(lambda: watcher.latest(four) is not None, what="QoS for 4")
                joined = watcher.latest(four)
                assert joined is not None
                # T = 7, 6, 6, 6: T_avg 6.25, R = 16 - 1 = 15 Hz, D = 749
                assert joined.robots["robot4"].rate_hz == pytest.approx(15.0)
                assert joined.robots["robot2"].depth == 749
                wait_until(lambda: bool(watcher.acked(joined.epoch, four)), what="4 acks")
                for ack in watcher.acked(joined.epoch, four).values():
                    assert ack.rate_hz == pytest.approx(15.0) and ack.depth == 749
                    assert (ack.stamp_ns - joined.stamp_ns) / 1e9 < 1.0, ack
                assert fourth.interrupt() == 0
            finally:
                fourth.kill()
            left_at = time.time_ns()
            wait_until(
                lambda: (m := watcher.latest(three)) is not None and m.epoch > joined.epoch,
                what="QoS for 3 again",
            )
            after = watcher.latest(three)
            assert after is not None and after.robots == before.robots
            wait_until(lambda: bool(watcher.acked(after.epoch, three)), what="3 acks again")
            for ack in watcher.acked(after.epoch, three).values():
                assert (ack.stamp_ns - left_at) / 1e9 < 1.0, ack
