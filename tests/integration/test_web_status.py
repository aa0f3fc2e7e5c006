"""The status page of a running fleet: a real CEDDP with ``web_port`` and three real robots
through its router, the page loaded in Debian's headless chromium, ``/metrics`` parsed with
Prometheus' own text parser and checked against ``/api/status``.

chromium runs with ``--dump-dom`` after a virtual-time budget: the page's JavaScript polls
``/api/status`` every (virtual) second and redraws, so the DOM it dumps shows what a person sees.
The test installs nothing; it skips only when /usr/bin/chromium is absent (CI installs it).

``ARPZ_STATUS_SCREENSHOT=docs/figures/status-page.png python -m pytest
tests/integration/test_web_status.py -k updates`` also saves a screenshot of the page there (the
figure of docs/tools.md "Live views").
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.integration.fleet import Process, ceddp, robots, settle, write_robot
from tests.support import free_port, wait_until

pytestmark = pytest.mark.integration

CHROMIUM = "/usr/bin/chromium"
ROBOTS = ("robot1", "robot2", "robot3")


def chromium(url: str, profile: Path, *action: str) -> str:
    """Run headless chromium on ``url`` for 3 s of virtual time (three or four redraws of the
    page) and do ``action`` (``--dump-dom``: return the DOM; ``--screenshot=FILE``)."""
    if shutil.which(CHROMIUM) is None:
        pytest.skip(f"{CHROMIUM} is absent (Debian's chromium package)")
    profile.mkdir(parents=True, exist_ok=True)
    result = subprocess.run(
        [
            CHROMIUM,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={profile}",
            "--virtual-time-budget=3000",
            *action,
            url,
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def received_in_dom(dom: str) -> dict[str, int]:
    """robot -> the received counter its row shows."""
    rows = re.findall(r'<tr id="robot-([^"]+)" data-received="(\d+)"', dom)
    return {robot: int(count) for robot, count in rows}


def get_json(port: int, path: str) -> Any:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as response:
        return json.loads(response.read())


def get_text(port: int, path: str) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as response:
        return str(response.read().decode())


def per_topic(status: dict[str, Any], field: str) -> dict[tuple[str, str], int]:
    return {(r["robot"], t["topic"]): t[field] for r in status["robots"] for t in r["topics"]}


def fleet_running(port: int) -> bool:
    status = get_json(port, "/api/status")
    alive = {r["robot"] for r in status["robots"] if r["alive"] and r["received"] > 0}
    return alive == set(ROBOTS) and status["metrics_stamp_ns"] > 0


def test_the_status_page_shows_a_running_fleet_and_updates(tmp_path: Path) -> None:
    port = free_port()
    grpc, rerun_web = free_port(), free_port()
    # QoS control on, so that the page has an assignment (epoch, R, D) to show, and the Rerun
    # web viewer, which the page links to
    extra = (
        f"web_port = {port}\ngrpc_port = {grpc}\nrerun_web_port = {rerun_web}\n"
        "[qos]\nenabled = true\n"
    )
    with ceddp(tmp_path, extra=extra) as (server, endpoint):
        configs = [
            write_robot(tmp_path, robot, endpoint, preset="machine2", rate_hz=20)
            for robot in ROBOTS
        ]
        with robots(tmp_path, configs):
            wait_until(lambda: fleet_running(port), timeout_s=15, what="3 robots on /api/status")
            url = f"http://127.0.0.1:{port}/"

            first = chromium(url, tmp_path / "profile1", "--dump-dom")
            shown = received_in_dom(first)
            assert set(shown) == set(ROBOTS), first[-3000:]
            polls = int(re.search(r'id="polls">(\d+)<', first).group(1))  # type: ignore[union-attr]
            assert polls >= 2, "the page did not redraw from /api/status"
            assert re.search(r'<span id="error"></span>', first), "the page shows an error"
            for robot in ROBOTS:  # the page's rows come from the live fleet
                assert shown[robot] > 0

            # a later load shows every robot's count higher (in CI one robot's stayed at 12
            # between two loads in a row, its readings mostly held back by the local cache: up
            # to 4 loads, a second apart)
            for attempt in range(4):
                settle(1.0)
                second = chromium(url, tmp_path / f"profile{attempt + 2}", "--dump-dom")
                again = received_in_dom(second)
                if all(again[r] > shown[r] for r in ROBOTS):
                    break
            assert all(again[r] > shown[r] for r in ROBOTS), (shown, again)
            link = re.search(r'<a id="rerun-link" href="([^"]+)"', second)
            assert link is not None, "no link to the Rerun web viewer"
            viewer = f"http://127.0.0.1:{rerun_web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}"
            assert link.group(1).startswith(viewer), link.group(1)
            assert "Rerun" in get_text(rerun_web, "/")  # the viewer is served

            before = get_json(port, "/api/status")
            text = get_text(port, "/metrics")
            after = get_json(port, "/api/status")
            screenshot = os.environ.get("ARPZ_STATUS_SCREENSHOT")
            if screenshot:  # for docs/tools.md "Live views": a fleet that has run for a while
                settle(8)
                shot = ("--window-size=1500,800", "--hide-scrollbars")
                target = f"--screenshot={Path(screenshot).resolve()}"
                chromium(url, tmp_path / "shot", *shot, target)
        families = {f.name: f for f in text_string_to_metric_families(text)}
        for name, field in (("arpz_samples_received", "received"), ("arpz_samples_lost", "lost")):
            assert families[name].type == "counter"
            scraped = {
                (s.labels["robot"], s.labels["topic"]): s.value
                for s in families[name].samples
                if s.name == f"{name}_total"
            }
            low, high = per_topic(before, field), per_topic(after, field)
            assert set(scraped) == set(low) == set(high)
            for slot, value in scraped.items():  # read at scrape time, between the two reads
                assert low[slot] <= value <= high[slot], (name, slot, low[slot], value)
        up = {s.labels["robot"]: s.value for s in families["arpz_robot_up"].samples}
        assert up == dict.fromkeys(ROBOTS, 1.0)
        assert server.interrupt() == 0, server.output()
    with pytest.raises(OSError):  # the page stops with the CEDDP
        socket.create_connection(("127.0.0.1", port), timeout=1).close()


def test_a_web_port_in_use_stops_the_start_with_a_sentence_naming_it(tmp_path: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        config = tmp_path / "ceddp.toml"
        config.write_text(
            f'fleet = "itest"\nlisten = ["tcp/127.0.0.1:{free_port()}"]\nweb_port = {port}\n'
            f'rrd = "{(tmp_path / "ceddp.rrd").as_posix()}"\n'
        )
        proc = Process("ceddp", ["-m", "arpz.ceddp", "--config", str(config)], tmp_path)
        try:
            code = proc.popen.wait(timeout=30)
        finally:
            proc.kill()
    assert code == 2, proc.output()
    assert f"web_port {port} on 127.0.0.1 cannot be served: in use" in proc.output()
    assert "Traceback" not in proc.output()
