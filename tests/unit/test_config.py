import subprocess
import sys
from pathlib import Path

import pytest

from arpz.core.config import CeddpConfig, ConfigError, RobotConfig, load_toml


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "robot.toml"
    path.write_text(text)
    return path


def test_a_good_robot_config_loads(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        'robot_id = "robot1"\npreset = "machine1"\n'
        '[[sensors]]\nname = "front"\nkind = "ultrasonic"\nrate_hz = 20\n',
    )
    config = load_toml(path, RobotConfig)
    assert config.robot_id == "robot1" and config.sensors[0].rate_hz == 20.0


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            'robot_id = "r1"\n[[sensors]]\nname = "a"\nkind = "pir"\nrate_hz = -1\n',
            "sensors[0]': rate_hz must be > 0",
        ),
        ('robot_id = "r1"\n[[sensors]]\nname = "a"\nkind = "sonar"\n', "sensors[0].kind"),
        ('robot_id = "r1"\nrate = 3\n', "unknown field `rate`"),
        (
            'robot_id = "r1"\n[local_cache]\nmax_silence = 3\n',
            "local_cache': Object contains unknown",
        ),
        ('robot_id = "Robot One"\n', "not a valid key chunk"),
        (
            'robot_id = "r1"\n[[sensors]]\nname = "a"\nkind = "pir"\n[[sensors]]\nname = "a"\n'
            'kind = "light"\n',
            "unique",
        ),
        ('robot_id = "r1"\n[[sensors]]\nname = "a"\nkind = "pir"\ndriver = "replay"\n', "trace"),
        ("robot_id = \n", "not valid TOML"),
    ],
)
def test_bad_configs_name_the_file_and_the_field(tmp_path: Path, text: str, expected: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_toml(path, RobotConfig)
    assert str(path) in str(info.value)
    assert expected in str(info.value)


def test_missing_file_and_ceddp_config(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        load_toml(tmp_path / "nope.toml", RobotConfig)
    path = tmp_path / "ceddp.toml"
    path.write_text('listen = ["tcp/0.0.0.0"]\n')
    with pytest.raises(ConfigError, match=r"listen\[0\] 'tcp/0.0.0.0': needs HOST:PORT"):
        load_toml(path, CeddpConfig)
    path.write_text("listen = []\n")  # empty: zenoh_config's endpoints, or the default
    assert load_toml(path, CeddpConfig).listen == []


def test_robot_cli_exits_2_with_the_message(tmp_path: Path) -> None:
    path = write(tmp_path, 'robot_id = "r1"\n[[sensors]]\nname = "a"\nkind = "pir"\nrate_hz = 0\n')
    result = subprocess.run(
        [sys.executable, "-m", "arpz.robot", "--config", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert str(path) in result.stderr and "sensors[0]" in result.stderr


def test_ceddp_cli_exits_2_with_the_message(tmp_path: Path) -> None:
    path = tmp_path / "ceddp.toml"
    path.write_text('fleet = "demo"\nlisten = ["tcp/127.0.0.1:1"]\nmetrics_period_s = "fast"\n')
    result = subprocess.run(
        [sys.executable, "-m", "arpz.ceddp", "--config", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert str(path) in result.stderr and "metrics_period_s" in result.stderr


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ('reliability = "best_effort"', 'the fleet\'s mode: "channel" or "none"'),
        ('[sensor_qos]\nreliability = "none"', 'reliability = "none" at the top of the file'),
    ],
)
def test_reliability_in_the_wrong_place_says_where_it_belongs(
    tmp_path: Path, text: str, expected: str
) -> None:
    """The demo's one --reliability flag covers the fleet's mode and a profile's policy; in a
    TOML file they are two settings, and the error says which one the value belongs to."""
    path = tmp_path / "robot.toml"
    path.write_text(f'robot_id = "r1"\npreset = "machine3"\n{text}\n')
    with pytest.raises(ConfigError) as caught:
        load_toml(path, RobotConfig)
    assert expected in str(caught.value) and "reliability" in str(caught.value)
