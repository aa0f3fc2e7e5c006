"""Actuation: commands from the CEDDP reach an ``Actuator``.

The agent decodes commands on its own worker thread (never on a Zenoh callback) and hands each
one to ``Actuator.apply``. ``RecordingActuator`` is the simulated actuator: it keeps the last
command per name and counts them, which is what tests and the demo look at. A real robot
subclasses ``Actuator`` and drives its motors in ``apply``, and brakes them in ``safe_stop``,
which the agent calls when a command's deadline passes with no new command
(arpz.robot.watchdog).
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

from arpz.core import keys
from arpz.core.config import PluginConfig, RobotConfig
from arpz.core.errors import ConfigError
from arpz.core.messages import (
    COMMAND_CONTRACT_DECODER,
    DECODE_ERRORS,
    Command,
    CommandContract,
    contract_clashes,
)
from arpz.core.transport import Transport
from arpz.runtime.plugins import load_class


class Actuator:
    """Base of every actuator. A team's actuator named in the robot's TOML (``[actuator]``) is
    made as ``cls(options)``; it sets ``commands`` to the command names it acts on."""

    #: the command names this actuator acts on: the robot reads ``cmd/{name}`` for each (through
    #: the reliable channel) and announces them, so the CEDDP opens a writer for each
    commands: Sequence[str] = ()
    #: the typed ones among them: name -> the ROS 2 type it accepts (``{"cmd_vel":
    #: "geometry_msgs/msg/Twist"}``); ``apply`` then gets the message as ``command.value``
    command_types: Mapping[str, str] = {}

    def __init__(self, options: Mapping[str, Any] | None = None) -> None:
        self.options: Mapping[str, Any] = options or {}

    def apply(self, name: str, command: Command) -> None:
        """Act on one command (``name`` is the command topic, e.g. "velocity"); a typed
        command's ``command.value`` is its message (the msgspec Struct of its type)."""
        raise NotImplementedError

    def stop(self) -> None:
        """Bring the robot to a safe state; called when the agent stops."""

    def safe_stop(self) -> None:
        """Stop moving: a command's deadline passed with no new command.

        The CEDDP died or the link is down, so the robot must not keep driving on its last
        command. The default calls ``stop()``; a hardware actuator overrides it to brake or zero
        its motors. It must be idempotent and quick (it runs on the agent's worker thread); the
        next ``apply`` resumes normal operation.
        """
        self.stop()


class RecordingActuator(Actuator):
    """Records commands instead of acting on them (a robot without actuators, and tests).

    It acts on no command unless given some: seed 001's machines 1-3 only sense, and eq. 1 of
    the QoS optimiser counts every command topic a robot announces."""

    def __init__(self, commands: Sequence[str] = ()) -> None:
        self.commands = tuple(commands)
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.last: dict[str, Command] = {}
        self.stopped = False
        #: safe stops so far, and whether the robot is in one now (cleared by the next apply)
        self.safe_stops = 0
        self.safe_stopped = False

    def apply(self, name: str, command: Command) -> None:
        with self._lock:
            self.counts[name] += 1
            self.last[name] = command
            self.safe_stopped = False

    def safe_stop(self) -> None:
        # recorded apart from stop(): ``stopped`` means the agent shut down
        with self._lock:
            self.safe_stops += 1
            self.safe_stopped = True

    def stop(self) -> None:
        self.stopped = True


class ActuatorConfigError(ConfigError):
    """A configured actuator that cannot be made, or that acts on no command."""


def make_actuator(entry: PluginConfig) -> Actuator:
    """The actuator ``[actuator]`` names, made with its options (before the robot connects, so
    that a wrong name or option stops it with a clear error)."""
    cls = load_class(entry.cls, Actuator, setting=f"actuator ({entry.cls})")
    try:
        actuator = cls(entry.options)
    except Exception as exc:
        raise ActuatorConfigError(
            f"actuator: {entry.cls}({dict(entry.options)!r}) raised {exc!r}"
        ) from exc
    if not actuator.commands or isinstance(actuator.commands, str):
        raise ActuatorConfigError(
            f"actuator {entry.cls}: set commands to the names it acts on, such as "
            f"('velocity',), got {actuator.commands!r}"
        )
    untyped = sorted(set(actuator.command_types) - set(actuator.commands))
    if untyped:
        raise ActuatorConfigError(
            f"actuator {entry.cls}: command_types names {', '.join(untyped)}, which commands "
            "does not list: list every command it acts on in commands"
        )
    return actuator


class CommandTypeError(ConfigError):
    """A planner of the fleet's CEDDP sends a command this robot's actuator takes as another
    type: the robot refuses to start rather than refuse every such command later."""


def check_command_contract(
    transport: Transport, config: RobotConfig, actuator: Actuator, *, timeout_s: float = 1.0
) -> CommandContract | None:
    """Ask the CEDDP what its planners send (``ceddp/commands``) and raise ``CommandTypeError``
    when one sends a command the actuator acts on as another type than the actuator takes.
    None when no CEDDP answered within ``timeout_s`` (none running yet, or access control
    without the right): the CEDDP then says so when the robot announces (docs/nodes.md)."""
    replies: list[bytes] = []
    got = threading.Event()

    def on_reply(payload: bytes) -> None:
        replies.append(payload)
        got.set()

    transport.request(keys.ceddp_commands_key(config.fleet), b"", on_reply, timeout_s=timeout_s)
    if not got.wait(timeout_s):
        return None
    try:
        contract = COMMAND_CONTRACT_DECODER.decode(replies[0])
    except DECODE_ERRORS:
        return None
    clashes = contract_clashes(contract, actuator.commands, actuator.command_types)
    if clashes:
        raise CommandTypeError(
            f"robot {config.robot_id}: " + "; ".join(clashes) + ": make the actuator's "
            "command_types and the planners' sends agree (docs/nodes.md)"
        )
    return contract
