"""A simulated body inside the robot process: what ``--sim hallway`` runs instead of hardware.

The body (arpz.mission) is stepped by the agent's scheduler thread, the only thread that touches it;
velocity commands reach it through a queue filled by the actuation worker. Its 8 LIDAR beams are
ordinary sensors to the rest of the agent (local cache, publishing, QoS), read from the ranges of
the last step, quantised to 1 cm as a real LIDAR's output is. The true pose goes out on the
telemetry key for the judge and the dashboard only.
"""

from __future__ import annotations

import queue
from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

from arpz.core.config import SensorConfig, SimConfig
from arpz.core.messages import Command
from arpz.mission import BEAM_ANGLES_DEG, Lidar, RobotBody, SimClock, World, beam_topic
from arpz.mission.world import BUILTIN_MAPS
from arpz.robot.actuation import Actuator
from arpz.robot.sensors.base import SensorDriver


class SimHost:
    def __init__(self, config: SimConfig, robot_id: str, *, seed: int, base_dir: Path) -> None:
        world_ref = config.world
        if world_ref not in BUILTIN_MAPS and not Path(world_ref).is_absolute():
            world_ref = str(base_dir / world_ref)
        self.world = World.load(world_ref)
        self.body = RobotBody(
            self.world,
            robot_id,
            lidar=Lidar(self.world, noise_std_m=config.noise_std_m, seed=seed),
        )
        self.clock = SimClock()
        self.commands: queue.SimpleQueue[tuple[float, float]] = queue.SimpleQueue()
        self.ranges: dict[str, float] = self.body.readings()
        self.commands_applied = 0

    def step(self, now_s: float) -> None:
        """Apply the commands that arrived, advance the body, take a LIDAR scan."""
        while True:
            try:
                v_m_s, omega_rad_s = self.commands.get_nowait()
            except queue.Empty:
                break
            self.body.apply_command(v_m_s, omega_rad_s)
            self.commands_applied += 1
        self.body.step(self.clock.tick())
        self.ranges = self.body.readings()

    def beam_sensors(self, rate_hz: float) -> list[SensorConfig]:
        return [
            SensorConfig(name=beam_topic(deg), kind="lidar", rate_hz=rate_hz, driver="sim-body")
            for deg in BEAM_ANGLES_DEG
        ]


class BeamDriver(SensorDriver):
    """One beam of the simulated LIDAR, as a sensor driver."""

    kind: ClassVar[str] = "lidar"

    def __init__(self, host: SimHost, topic: str) -> None:
        super().__init__({}, 0)
        self.host = host
        self.topic = topic

    def read(self, now_s: float) -> float:
        return round(self.host.ranges[self.topic], 2)


class SimActuator(Actuator):
    """Velocity commands ``[v_m_s, omega_rad_s]`` on ``cmd/velocity`` drive the simulated body."""

    commands: Sequence[str] = ("velocity",)

    def __init__(self, host: SimHost) -> None:
        self.host = host
        self.rejected = 0

    def apply(self, name: str, command: Command) -> None:
        value: Any = command.value
        if name != "velocity" or not (isinstance(value, list) and len(value) == 2):
            self.rejected += 1
            raise ValueError(
                f"expected cmd/velocity with [v_m_s, omega_rad_s], got {name} {value!r}"
            )
        self.host.commands.put((float(value[0]), float(value[1])))

    def stop(self) -> None:
        self.host.commands.put((0.0, 0.0))

    def safe_stop(self) -> None:
        """Zero velocity, as ``stop`` (the queue is thread-safe; the next step applies it)."""
        self.host.commands.put((0.0, 0.0))
