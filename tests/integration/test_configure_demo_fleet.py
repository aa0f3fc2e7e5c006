"""characterise against a real fleet: ``python -m arpz.ceddp`` and two ``python -m arpz.robot``
processes started as ``python -m arpz demo`` starts them."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest

from arpz.configure.model import load_model
from arpz.tools.demo import DemoOptions, demo_spec
from arpz.tools.launch import free_port, run_fleet
from tests.integration.test_configure_characterise import characterise

pytestmark = pytest.mark.integration


def test_characterise_a_running_demo_fleet(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    spec = demo_spec(
        DemoOptions(robots=2, duration_s=30, rate_hz=20.0, rrd=tmp_path / "demo.rrd"), endpoint
    )
    result: dict[str, Any] = {}
    characterised = threading.Event()

    def fleet() -> None:
        try:
            result["summary"] = run_fleet(
                spec,
                tmp_path / "fleet",
                duration_s=60,
                until=lambda _ceddp: characterised.is_set(),
                progress=None,
            )
        except Exception as exc:  # reported by the assertion below
            result["error"] = exc

    runner = threading.Thread(target=fleet)
    runner.start()
    out = tmp_path / "fleet.json"
    try:
        proc = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and "error" not in result:
            proc = characterise(endpoint, "demo", 4, str(out))
            if proc.returncode == 0 and "robot2_agent" in proc.stdout:
                break
            time.sleep(0.5)
    finally:
        characterised.set()
        runner.join(timeout=90)
    assert "error" not in result, result.get("error")
    assert proc is not None and proc.returncode == 0, (proc.stdout, proc.stderr) if proc else None
    model = load_model(out)
    assert {c.name for c in model.computers} == {"robot1", "robot2", "server"}
    nodes = {n.name: n for n in model.nodes}
    assert set(nodes) == {"robot1_agent", "robot2_agent", "ceddp"}
    # real processes use real CPU and their topics real bandwidth
    assert nodes["ceddp"].settings[0].cpu > 0
    assert all(m.bandwidth > 0 for m in model.messages)
    assert "overall sum(w P)" in proc.stdout
