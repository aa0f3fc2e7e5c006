"""A planner's commands (PlannerCommands): values for a value command, whole messages of the
type the robot announced for a typed one, checked before they leave; one seq per key."""

from __future__ import annotations

import msgspec
import pytest

from arpz.ceddp.planner import PlannerCommands
from arpz.core.messages import COMMAND_DECODER, MESSAGE_COMMAND_DECODER
from arpz.core.msgtypes import MessageTypes, MessageValueError

TWIST = "geometry_msgs/msg/Twist"
TYPES = MessageTypes()


class Sink:
    def __init__(self) -> None:
        self.sent: list[tuple[str, str, bytes]] = []

    def send(self, robot: str, name: str, payload: bytes) -> None:
        self.sent.append((robot, name, payload))


def commands(sink: Sink) -> PlannerCommands:
    types = {("robot1", "cmd_vel"): TWIST}
    return PlannerCommands(
        sink, "ceddp:abc", command_type=lambda r, n: types.get((r, n)), types=TYPES
    )


def twist(x: float) -> dict[str, dict[str, float]]:
    return {"linear": {"x": x, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.5}}


def test_a_typed_command_goes_out_as_its_message_and_a_value_command_as_a_value() -> None:
    sink = Sink()
    out = commands(sink)
    out.send("robot1", "cmd_vel", twist(0.25))
    out.send("robot1", "cmd_vel", twist(0.5))
    out.send("robot1", "velocity", [0.1, 0.0])
    (_, _, first), (_, _, second), (_, name, value) = sink.sent
    sent = [MESSAGE_COMMAND_DECODER.decode(p) for p in (first, second)]
    assert [s.seq for s in sent] == [1, 2]
    assert TYPES.decode(TWIST, sent[1].value).linear.x == 0.5
    assert name == "velocity" and COMMAND_DECODER.decode(value).value == [0.1, 0.0]


def test_a_command_that_does_not_fit_is_refused_before_it_leaves() -> None:
    sink = Sink()
    out = commands(sink)
    with pytest.raises(MessageValueError, match="linear"):
        out.send("robot1", "cmd_vel", {"linear": {"x": "fast"}, "angular": {}})
    with pytest.raises(MessageValueError, match="takes velocity as a value"):
        out.send("robot1", "velocity", twist(0.1))
    struct = TYPES.check(TWIST, twist(0.1))
    out.send("robot1", "cmd_vel", struct)
    (_, _, payload) = sink.sent[0]
    assert MESSAGE_COMMAND_DECODER.decode(payload).seq == 1  # the refused ones left no hole
    assert isinstance(struct, msgspec.Struct)
