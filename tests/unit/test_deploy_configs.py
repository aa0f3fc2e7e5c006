"""The example configurations in deploy/ must load and build their drivers."""

import re
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


def test_every_doc_the_deploy_files_name_exists() -> None:
    """deploy/ceddp.toml once linked docs/tools-live.md, which did not exist (issue 41)."""
    named = {
        match
        for path in DEPLOY.rglob("*")
        if path.is_file() and path.suffix in (".toml", ".py", ".json5", ".service", ".md")
        for match in re.findall(r"docs/[\w./-]+?\.md", path.read_text(encoding="utf-8"))
    }
    assert named, "the deploy files name no doc: the pattern is wrong"
    missing = sorted(doc for doc in named if not (DEPLOY.parent / doc).is_file())
    assert not missing, missing
