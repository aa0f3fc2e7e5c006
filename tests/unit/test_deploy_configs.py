"""The example configurations in deploy/ must load and build their drivers."""

from pathlib import Path

import pytest

from arpz.core.config import CeddpConfig, RobotConfig, load_toml
from arpz.robot.agent import effective_sensors
from arpz.robot.sensors import make_driver

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


@pytest.mark.parametrize("name", ["robot1.toml", "robot3.toml"])
def test_robot_examples_load_and_their_drivers_read(name: str) -> None:
    config = load_toml(DEPLOY / name, RobotConfig)
    sensors = effective_sensors(config)
    assert sensors
    for sensor in sensors:
        driver = make_driver(sensor, robot_id=config.robot_id, robot_seed=0, base_dir=DEPLOY)
        driver.read(0.5)


def test_ceddp_example_loads() -> None:
    config = load_toml(DEPLOY / "ceddp.toml", CeddpConfig)
    assert config.hello.relay == "robot3"
