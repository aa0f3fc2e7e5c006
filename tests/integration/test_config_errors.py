"""Configuration errors outside TOML exit 2 with a sentence naming the file and the field.

Real processes (``python -m arpz.robot`` / ``arpz.ceddp``) and real Zenoh JSON5 files and
certificates made by the deploy script; nothing here needs a running router except the last test,
which proves the unreachable-server message names the endpoint, the TLS identity and the time.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.integration.fleet import free_port
from tests.integration.secure_fleet import client_config, make_fleet_tls

pytestmark = pytest.mark.integration


def run(module: str, config: Path, timeout_s: float = 30) -> tuple[int, str]:
    proc = subprocess.run(
        [sys.executable, "-m", module, "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=config.parent,
    )
    return proc.returncode, proc.stdout + proc.stderr


def robot_toml(tmp: Path, body: str) -> Path:
    path = tmp / "robot.toml"
    path.write_text(f'robot_id = "robot1"\npreset = "machine3"\nconnect_timeout_s = 1\n{body}\n')
    return path


TOML = "robot.toml: "
ZCONF = TOML + "field 'zenoh_config': "


@pytest.mark.parametrize(
    ("body", "expected"),
    [
        ('zenoh_config = "missing.json5"', ZCONF + "missing.json5: no such file"),
        ('zenoh_config = "broken.json5"', ZCONF + "broken.json5 is not a valid Zenoh config"),
        (
            'zenoh_config = "nocert.json5"',
            "nocert.json5: transport.link.tls.connect_certificate: /nope/robot1.pem: no such file",
        ),
        (
            'zenoh_config = "badendpoint.json5"',
            "badendpoint.json5: connect.endpoints[0] 'tls/ceddp.local'",
        ),
        ('connect = ["tcp/127.0.0.1"]', TOML + "connect[0] 'tcp/127.0.0.1': needs HOST:PORT"),
        (
            'connect = ["foo/127.0.0.1:7447"]',
            TOML + "connect[0] 'foo/127.0.0.1:7447': an endpoint is PROTOCOL/ADDRESS",
        ),
    ],
)
def test_robot_config_errors_exit_2_naming_file_and_field(
    tmp_path: Path, body: str, expected: str
) -> None:
    (tmp_path / "broken.json5").write_text('{ mode: "client",, }')
    (tmp_path / "nocert.json5").write_text(
        '{ transport: { link: { tls: { connect_certificate: "/nope/robot1.pem" } } } }'
    )
    (tmp_path / "badendpoint.json5").write_text('{ connect: { endpoints: ["tls/ceddp.local"] } }')
    code, out = run("arpz.robot", robot_toml(tmp_path, body))
    assert code == 2, out
    assert expected in out, out
    assert ".rs:" not in out, out  # no Rust source path


def test_the_ceddp_takes_the_json5s_tls_endpoint_and_refuses_plain_tcp_beside_it(
    tmp_path: Path,
) -> None:
    tls = make_fleet_tls(tmp_path / "tls", "cfg", ["robot1"])
    port = free_port()
    router = tmp_path / "router.json5"  # the script's file, on a free port for the test
    router.write_text(
        (tls / "zenoh" / "ceddp-router.json5")
        .read_text()
        .replace('"tls/0.0.0.0:7447"', f'"tls/127.0.0.1:{port}"')
        .replace('"quic/0.0.0.0:7447"', f'"quic/127.0.0.1:{port}"')
    )
    assert f"tls/127.0.0.1:{port}" in router.read_text()
    config = tmp_path / "ceddp.toml"
    # the TOML lists a plain tcp/ endpoint next to the JSON5's TLS setup: refused
    config.write_text(
        f'fleet = "cfg"\nzenoh_config = "{router}"\nlisten = ["tcp/127.0.0.1:{port}"]\n'
    )
    code, out = run("arpz.ceddp", config)
    assert code == 2, out
    assert f"listen[0] 'tcp/127.0.0.1:{port}' is plain TCP" in out and "allow_plain_tcp" in out
    # the TOML says nothing: the JSON5's endpoints (tls/) are used, not a plain tcp/ default
    config.write_text(
        f'fleet = "cfg"\nzenoh_config = "{router}"\nduration_s = 0.5\n'
        f'rrd = "{tmp_path / "c.rrd"}"\n'
    )
    code, out = run("arpz.ceddp", config, timeout_s=60)
    assert code == 0, out
    ready = f"ready on quic/127.0.0.1:{port},tls/127.0.0.1:{port}"
    assert ready in out and "tcp/" not in out.split("ready on")[1].split(" ")[0], out


def test_an_unreachable_server_names_endpoint_identity_and_time(tmp_path: Path) -> None:
    tls = make_fleet_tls(tmp_path / "tls", "cfg", ["robot1"])
    endpoint = f"tls/127.0.0.1:{free_port()}"  # nobody listens there
    body = f'connect = ["{endpoint}"]\nzenoh_config = "{client_config(tls, "robot1")}"'
    code, out = run("arpz.robot", robot_toml(tmp_path, body))
    assert code == 1, out
    assert endpoint in out and "TLS identity" in out and "robot1.pem" in out, out
    assert "tried for 1 s" in out and ".rs:" not in out, out
