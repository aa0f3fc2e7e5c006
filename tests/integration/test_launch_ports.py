"""A port ``free_port`` found free can be taken by another process before the CEDDP binds it
(seen in CI: parallel tests). The launcher tells that apart from other failures, and the demo
and the experiment runner start again on new ports. Real CEDDP and robot processes."""

from __future__ import annotations

import io
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

import arpz.experiment.runner
import arpz.tools.demo
from arpz.core.transport import TransportError
from arpz.experiment.presets import quick
from arpz.tools.demo import DemoOptions, demo_spec, run_demo
from arpz.tools.launch import PortTaken, free_port, run_fleet
from tests import support
from tests.integration import fleet

pytestmark = pytest.mark.integration


@contextmanager
def taken_port(kind: int = socket.SOCK_STREAM) -> Iterator[int]:
    """A loopback port another socket holds (TCP: listening) for the duration."""
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        if kind == socket.SOCK_STREAM:
            sock.listen()
        yield int(sock.getsockname()[1])


def test_a_ceddp_whose_port_is_taken_raises_port_taken(tmp_path: Path) -> None:
    with taken_port() as port:
        spec = demo_spec(DemoOptions(robots=1, rrd=tmp_path / "x.rrd"), f"tcp/127.0.0.1:{port}")
        with pytest.raises(PortTaken, match="Address already in use"):
            run_fleet(spec, tmp_path / "fleet", duration_s=1, progress=None)


def test_the_demo_starts_again_on_a_new_port(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with taken_port() as port:
        ports = iter([port])  # the first pick is taken, the next is really free
        monkeypatch.setattr(arpz.tools.demo, "free_port", lambda: next(ports, None) or free_port())
        progress = io.StringIO()
        options = DemoOptions(robots=1, duration_s=2, rate_hz=20.0, rrd=tmp_path / "demo.rrd")
        summary = run_demo(options, tmp_path / "demo", progress)
    assert "port was taken" in progress.getvalue()
    assert summary["robots"]["robot1"]["received"] > 0, summary["robots"]


def test_an_experiment_cell_starts_again_on_new_ports(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = quick()
    cell = spec.cells()[0]
    with taken_port(socket.SOCK_DGRAM) as port:
        picks = iter([port])  # the CEDDP's UDP listener first, on a taken port

        def pick(kind: int = socket.SOCK_STREAM) -> int:
            taken = next(picks, None) if kind == socket.SOCK_DGRAM else None
            return taken or free_port(kind)

        monkeypatch.setattr(arpz.experiment.runner, "free_port", pick)
        row = arpz.experiment.runner.run_cell(spec, cell, tmp_path / "out")
    assert "a port was taken" in capsys.readouterr().err
    assert row["status"] == "ok", row["error"]
    assert int(row["samples_sent"]) > 0


def test_the_tests_router_takes_a_new_port_when_its_first_is_taken(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``tests.support.router``, which most integration tests start: the same race, the same
    answer. A port given explicitly is not replaced."""
    with taken_port() as port:
        offered = iter([port])
        monkeypatch.setattr(support, "free_port", lambda: next(offered, None) or free_port())
        with support.router() as (_, endpoint):
            assert endpoint.startswith("tcp/127.0.0.1:") and not endpoint.endswith(f":{port}")
            with support.client(endpoint):  # it listens there
                pass
        with pytest.raises(TransportError, match="in use"), support.router(port):
            pass


def test_the_tests_ceddp_starts_again_when_its_port_is_taken(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """``tests.integration.fleet.ceddp``, behind most fleet tests: a real CEDDP process that
    finds its port taken exits, and the helper starts another on a new port."""
    with taken_port() as port:
        offered = iter([port])
        monkeypatch.setattr(fleet, "free_port", lambda: next(offered, None) or free_port())
        with fleet.ceddp(tmp_path) as (proc, endpoint):
            assert not endpoint.endswith(f":{port}")
            assert proc.popen.poll() is None
