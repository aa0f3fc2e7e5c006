"""The command watchdog (pure, times passed explicitly) and the actuators' safe_stop."""

import math
from pathlib import Path

import pytest

from arpz.core.config import SimConfig
from arpz.core.messages import Command
from arpz.robot.actuation import Actuator, RecordingActuator
from arpz.robot.sim_host import SimActuator, SimHost
from arpz.robot.watchdog import CommandWatchdog


def test_a_name_never_commanded_is_not_armed() -> None:
    watchdog = CommandWatchdog({"velocity": 0.5})
    assert watchdog.check(0.0) == []
    assert watchdog.check(100.0) == []
    assert watchdog.next_expiry_s() is None
    assert watchdog.total_stops == 0
    assert watchdog.snapshot() == {"stops": {"velocity": 0}, "stopped": []}


def test_fires_once_after_the_deadline() -> None:
    watchdog = CommandWatchdog({"velocity": 0.5})
    assert watchdog.on_command("velocity", 10.0) is False
    assert watchdog.next_expiry_s() == 10.5
    assert watchdog.check(10.25) == []
    assert watchdog.check(10.5) == ["velocity"]  # the deadline passes at last command + 0.5 s
    assert watchdog.check(10.75) == []  # reported once
    assert watchdog.check(60.0) == []
    assert watchdog.stops == {"velocity": 1}
    assert watchdog.total_stops == 1
    assert watchdog.stopped == {"velocity"}
    assert watchdog.last_stop_s == 10.5
    assert watchdog.next_expiry_s() is None
    assert watchdog.snapshot() == {"stops": {"velocity": 1}, "stopped": ["velocity"]}


def test_commands_in_time_keep_it_from_firing() -> None:
    watchdog = CommandWatchdog({"velocity": 0.5})
    for tick in range(100):  # a 10 Hz planner
        now_s = tick * 0.1
        assert watchdog.on_command("velocity", now_s) is False
        assert watchdog.check(now_s + 0.05) == []
    assert watchdog.total_stops == 0


def test_the_next_command_resumes_and_re_arms() -> None:
    watchdog = CommandWatchdog({"velocity": 0.5})
    watchdog.on_command("velocity", 0.0)
    assert watchdog.check(1.0) == ["velocity"]
    assert watchdog.on_command("velocity", 5.0) is True  # resumed
    assert watchdog.stopped == set()
    assert watchdog.on_command("velocity", 5.25) is False  # not stopped any more
    assert watchdog.check(5.5) == []  # re-armed from the last command
    assert watchdog.check(5.75) == ["velocity"]
    assert watchdog.check(6.0) == []
    assert watchdog.stops == {"velocity": 2}
    assert watchdog.total_stops == 2
    assert watchdog.last_stop_s == 5.75


def test_several_names_with_their_own_deadlines() -> None:
    watchdog = CommandWatchdog({"velocity": 0.5, "arm": 2.0, "gripper": 1.0})
    watchdog.on_command("velocity", 0.0)
    watchdog.on_command("arm", 0.0)
    watchdog.on_command("gripper", 0.25)
    assert watchdog.next_expiry_s() == 0.5
    assert watchdog.check(0.5) == ["velocity"]
    assert watchdog.next_expiry_s() == 1.25
    assert watchdog.check(1.0) == []
    assert watchdog.check(3.0) == ["arm", "gripper"]  # sorted
    assert watchdog.stopped == {"velocity", "arm", "gripper"}
    assert watchdog.on_command("arm", 4.0) is True
    assert watchdog.snapshot() == {
        "stops": {"velocity": 1, "arm": 1, "gripper": 1},
        "stopped": ["gripper", "velocity"],
    }
    assert watchdog.total_stops == 3


def test_a_name_without_a_deadline_never_fires() -> None:
    watchdog = CommandWatchdog({"velocity": 0.5})
    assert watchdog.on_command("lights", 0.0) is False
    assert watchdog.check(1000.0) == []
    assert watchdog.on_command("lights", 2000.0) is False
    assert "lights" not in watchdog.stops
    assert watchdog.next_expiry_s() is None
    assert CommandWatchdog({}).check(1.0) == []


@pytest.mark.parametrize("deadline_s", [0.0, -0.5, math.nan])
def test_a_bad_deadline_is_refused_naming_the_command(deadline_s: float) -> None:
    with pytest.raises(ValueError, match="'velocity'"):
        CommandWatchdog({"arm": 1.0, "velocity": deadline_s})


def test_the_deadlines_are_copied() -> None:
    deadlines_s = {"velocity": 0.5}
    watchdog = CommandWatchdog(deadlines_s)
    deadlines_s["velocity"] = 100.0
    watchdog.on_command("velocity", 0.0)
    assert watchdog.check(0.5) == ["velocity"]


def test_the_default_safe_stop_calls_stop() -> None:
    class Motors(Actuator):
        def __init__(self) -> None:
            self.stops = 0

        def stop(self) -> None:
            self.stops += 1

    motors = Motors()
    motors.safe_stop()
    assert motors.stops == 1


def test_recording_actuator_records_safe_stops_until_the_next_command() -> None:
    actuator = RecordingActuator()
    assert (actuator.safe_stops, actuator.safe_stopped) == (0, False)
    actuator.apply("velocity", Command("ceddp:x", 1, 0, [0.5, 0.0]))
    actuator.safe_stop()
    actuator.safe_stop()  # idempotent: still one stop in force, both counted
    assert (actuator.safe_stops, actuator.safe_stopped) == (2, True)
    assert actuator.stopped is False  # a safe stop is not the agent's shutdown
    actuator.apply("velocity", Command("ceddp:x", 2, 0, [0.5, 0.0]))
    assert (actuator.safe_stops, actuator.safe_stopped) == (2, False)
    assert actuator.counts["velocity"] == 2


def test_sim_actuator_safe_stop_zeroes_the_body() -> None:
    host = SimHost(
        SimConfig(world="hallway_small", noise_std_m=0.0), "robot1", seed=0, base_dir=Path(".")
    )
    actuator = SimActuator(host)
    actuator.apply("velocity", Command("ceddp:x", 1, 0, [0.5, 0.0]))
    actuator.safe_stop()
    assert host.commands.get_nowait() == (0.5, 0.0)
    assert host.commands.get_nowait() == (0.0, 0.0)
    actuator.apply("velocity", Command("ceddp:x", 2, 0, [0.5, 0.0]))
    actuator.safe_stop()
    host.step(0.0)  # both queued commands applied in order: the body is at rest
    assert host.commands_applied == 2
    assert host.body.command == (0.0, 0.0)
    assert actuator.rejected == 0
