"""The robot's watch on its link to the CEDDP (issue 39): when a drop is noticed, when the session
is reopened, when the link is back. A fake clock drives ``LinkMonitor``; ``LinkWatch`` and the
agent's signals run on the in-memory bus."""

from __future__ import annotations

import itertools
import json
import logging
import threading
from pathlib import Path

import pytest

from arpz.core.config import LinkConfig, RobotConfig
from arpz.core.transport import TransportError
from arpz.robot.agent import RobotAgent
from arpz.robot.link_monitor import LinkMonitor, LinkWatch, Signals, Waiting, route_sources
from arpz.robot.summary import RobotSummary
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until

UP = Signals(heard=0, asked=0, present=True, route=("10.0.1.2",))


class Run:
    """A monitor and a fake clock: ``step`` advances the clock and takes a reading."""

    def __init__(self, config: LinkConfig | None = None) -> None:
        self.now = 100.0
        self.wall = 1_000.0
        self.monitor = LinkMonitor(config or LinkConfig(), self.now, wall_s=lambda: self.wall)
        self.heard = 0
        self.asked = 0
        self.present: bool | None = True
        self.route: tuple[str, ...] | None = ("10.0.1.2",)
        self.reopens: list[float] = []

    def step(self, dt: float = 0.1, *, heard: int = 0, asked: int = 0) -> bool:
        self.now += dt
        self.wall += dt
        self.heard += heard
        self.asked += asked
        reopen = self.monitor.observe(
            self.now, Signals(self.heard, self.asked, self.present, self.route)
        )
        if reopen:
            self.reopens.append(self.now)
        return reopen

    def run(self, seconds: float, *, heard: int = 0, asked: int = 1) -> None:
        """Readings every 0.1 s for ``seconds``, each with ``heard``/``asked`` more."""
        for _ in range(round(seconds / 0.1)):
            self.step(heard=heard, asked=asked)


def test_a_talking_ceddp_is_never_lost() -> None:
    run = Run()
    run.run(60.0, heard=1, asked=1)
    assert not run.monitor.lost and run.monitor.drops() == []


def test_a_quiet_robot_that_asks_nothing_is_not_silent() -> None:
    run = Run()
    run.step(heard=1)
    run.run(30.0, asked=0)
    assert not run.monitor.lost


def test_silence_while_data_waits_is_a_drop_then_a_reopen_after_the_grace(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, "arpz.robot.link")
    run = Run(LinkConfig(silence_s=3.0, zenoh_grace_s=1.0))
    run.run(1.0, heard=1, asked=1)
    run.run(2.9)  # asking, hearing nothing: not yet
    assert not run.monitor.lost
    run.run(0.2)
    assert run.monitor.lost
    [drop] = run.monitor.drops()
    assert drop.reason.startswith("nothing heard from the CEDDP for 3.")
    assert drop.back_at is None and 3.0 <= drop.silent_s <= 3.2
    assert "link to the CEDDP lost: nothing heard" in caplog.text
    lost_at = run.now
    run.run(0.8)
    assert run.reopens == []  # Zenoh's own session gets its grace
    run.run(0.3)
    assert len(run.reopens) == 1 and run.reopens[0] - lost_at == pytest.approx(1.0, abs=0.11)


def test_zenoh_coming_back_by_itself_within_the_grace_needs_no_reopen(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, "arpz.robot.link")
    run = Run()
    run.run(4.0)  # silent from the start while asking
    assert run.monitor.lost
    run.step(heard=1)
    assert not run.monitor.lost and run.reopens == []
    [drop] = run.monitor.drops()
    assert drop.back_at is not None and not drop.reopened and drop.reopen_attempts == 0
    assert "reconnected after" in caplog.text and "came back by itself" in caplog.text


def test_a_roam_reopens_at_once_and_the_new_address_is_the_baseline() -> None:
    run = Run()
    run.run(1.0, heard=1)
    run.route = ("10.0.2.2",)
    assert run.step(heard=1)  # heard or not: the old session is on an address that is gone
    [drop] = run.monitor.drops()
    assert "10.0.1.2 -> 10.0.2.2" in drop.reason and drop.silent_s < 0.2
    run.monitor.attempt_done(run.now, True)
    run.present = False  # the reopen: the watcher is told the CEDDP vanished...
    run.step()
    assert run.monitor.lost
    run.present = True  # ...and the new session's history says it is there
    run.step(heard=1)
    assert not run.monitor.lost
    [drop] = run.monitor.drops()
    assert drop.reopened and drop.reopen_attempts == 1 and drop.duration_s == pytest.approx(0.2)
    run.run(5.0, heard=1)  # on the new address from now on
    assert len(run.monitor.drops()) == 1


def test_no_route_is_a_drop_and_the_link_is_not_back_before_a_route_is() -> None:
    run = Run()
    run.run(1.0, heard=1)
    run.route = ()
    assert run.step()
    assert run.monitor.drops()[0].reason == "no route to the CEDDP"
    run.monitor.attempt_done(run.now, False, "network unreachable")
    run.step(heard=1)
    assert run.monitor.lost  # heard (a stale callback), but no route
    run.route = ("10.0.1.2",)
    run.step(heard=1)
    assert not run.monitor.lost


def test_a_vanished_presence_waits_for_zenoh_then_reopens() -> None:
    run = Run(LinkConfig(zenoh_grace_s=1.0))
    run.run(1.0, heard=1)
    run.present = False
    run.step()
    assert run.monitor.lost and "presence vanished" in run.monitor.drops()[0].reason
    run.run(0.9)
    assert run.reopens == []
    run.run(0.2)
    assert len(run.reopens) == 1


def test_heard_without_the_presence_is_not_back() -> None:
    run = Run()
    run.run(1.0, heard=1)
    run.present = False
    run.step()
    run.step(heard=3)  # late callbacks of the dead session
    assert run.monitor.lost


def test_failed_attempts_back_off_from_their_start_and_never_busy_loop() -> None:
    config = LinkConfig(reopen_backoff_s=0.25, reopen_backoff_max_s=1.5, zenoh_grace_s=0.0)
    run = Run(config)
    run.run(1.0, heard=1)
    run.route = ()  # no route: every attempt fails at once
    starts = []
    for _ in range(200):  # 20 s
        if run.step():
            starts.append(run.now)
            run.monitor.attempt_done(run.now, False, "no route")
    gaps = [b - a for a, b in itertools.pairwise(starts)]
    # each at the first 0.1 s reading at or after the backoff: 0.25, 0.5, 1, then 1.5 s
    for gap, backoff in zip(gaps, [0.25, 0.5, 1.0, *[1.5] * 20], strict=False):
        assert backoff - 1e-6 <= gap <= backoff + 0.1 + 1e-6, gaps
    assert run.monitor.reopen_attempts == len(starts) <= 20


@pytest.mark.parametrize("timeout_s", [1.5, 0.5])
def test_an_attempt_that_spent_its_timeout_is_followed_at_once(timeout_s: float) -> None:
    run = Run(LinkConfig(zenoh_grace_s=0.0))
    run.run(1.0, heard=1)
    run.route = ()
    assert run.step()
    for _ in range(5):  # attempts that each waited out Zenoh's open_timeout on a dead link
        started = run.now
        run.now += timeout_s
        run.monitor.attempt_done(run.now, False, "deadline has elapsed")
        assert run.step(dt=0.1), "the next attempt must start at the next reading"
        assert run.now - started == pytest.approx(timeout_s + 0.1)


def test_an_opened_session_gets_time_to_prove_itself_then_another_try() -> None:
    run = Run(LinkConfig(silence_s=3.0, zenoh_grace_s=0.0))
    run.run(1.0, heard=1)
    run.route = ("10.0.2.2",)
    assert run.step()
    run.monitor.attempt_done(run.now, True)
    run.run(2.9, asked=1)  # the new session brings nothing
    assert run.reopens[-1] < run.now - 2.8
    run.run(0.2, asked=1)
    assert len(run.reopens) == 2


def test_the_summary_counts_drops_reconnections_and_durations() -> None:
    run = Run()
    run.run(1.0, heard=1)
    run.route = ("10.0.2.2",)
    run.step()
    run.monitor.attempt_done(run.now, False, "refused")
    run.run(0.5)
    run.monitor.attempt_done(run.now, True)
    run.step(heard=1)
    run.run(10.0, heard=1)
    run.route = ()
    run.step()
    summary = run.monitor.summary()
    assert summary["drops"] == 2 and summary["reconnections"] == 1 and summary["lost_now"]
    assert summary["reopen_attempts"] == 2 and summary["reopens"] == 1
    events = summary["events"]
    assert isinstance(events, list)
    first, second = events
    assert first["reopened"] and first["duration_s"] == pytest.approx(0.6, abs=0.01)
    assert first["outage_s"] >= first["duration_s"] and first["back_at"] > first["lost_at"]
    assert second["back_at"] is None and second["reason"] == "no route to the CEDDP"
    json.dumps(summary)  # JSON as it is


def test_waiting_counts_only_what_a_matched_reliable_reader_has_not_acknowledged() -> None:
    waiting = Waiting()
    assert waiting.update([("a", False, 10, 10)]) == 0  # nobody matched: nobody waits
    assert waiting.update([("a", False, 12, 12)]) == 0
    assert waiting.update([("a", True, 12, 15)]) == 3  # 13..15 wait for the reader
    assert waiting.update([("a", True, 15, 15)]) == 3  # acknowledged: nothing more asked
    assert waiting.update([("a", True, 16, 16)]) == 3  # a best-effort reader: never waits
    assert waiting.update([("a", True, 16, 18), ("b", True, 0, 2)]) == 7


def test_route_sources_reads_the_kernels_choice_without_sending() -> None:
    assert route_sources([("127.0.0.1", 7447)]) == ("127.0.0.1",)
    assert route_sources([("127.0.0.1", 7447), ("::1", 7447)])[0] == "127.0.0.1"


@pytest.mark.parametrize(
    "field", ["silence_s", "reopen_backoff_s", "reopen_backoff_max_s", "check_period_s"]
)
def test_link_config_refuses_non_positive_times(field: str) -> None:
    with pytest.raises(ValueError, match=field):
        LinkConfig(**{field: 0.0})  # type: ignore[arg-type]


def test_link_config_refuses_a_maximum_backoff_below_the_first() -> None:
    with pytest.raises(ValueError, match="reopen_backoff_max_s"):
        LinkConfig(reopen_backoff_s=1.0, reopen_backoff_max_s=0.5)


class FlakyTransport(MemoryTransport):
    """A memory transport whose first ``fail`` reopens raise, as on a dead link."""

    def __init__(self, bus: MemoryBus, fail: int) -> None:
        super().__init__(bus)
        self.fail = fail
        self.attempts = 0

    def reopen(self) -> None:
        self.attempts += 1
        if self.attempts <= self.fail:
            raise TransportError("Unable to connect")
        super().reopen()


def test_the_watch_reopens_on_its_thread_until_the_link_is_back() -> None:
    bus = MemoryBus()
    transport = FlakyTransport(bus, fail=2)
    heard = [0]
    lost = threading.Event()
    read = threading.Event()
    route = [("10.0.1.2",)]

    def signals() -> Signals:
        read.set()
        return Signals(heard[0], 0, True, route[0])

    config = LinkConfig(check_period_s=0.01, reopen_backoff_s=0.02, reopen_backoff_max_s=0.02)
    watch = LinkWatch(config, transport, signals, on_change=lost.set)
    watch.start()
    try:
        assert read.wait(5)  # the first reading is the baseline: the roam comes after it
        route[0] = ("10.0.2.2",)
        assert lost.wait(5)
        wait_until(lambda: transport.reopens == 1, what="the third attempt to open")
        heard[0] += 1
        wait_until(lambda: not watch.monitor.lost, what="the link back")
    finally:
        watch.stop()
    [drop] = watch.monitor.drops()
    assert drop.reopen_attempts == 3 and drop.reopened and transport.attempts == 3


def _agent(bus: MemoryBus, tmp_path: Path) -> RobotAgent:
    config = RobotConfig(
        robot_id="r1",
        fleet="f",
        preset="machine2",
        match_timeout_s=0.01,
        connect=["tcp/127.0.0.1:7447"],
    )
    return RobotAgent(config, MemoryTransport(bus), base_dir=tmp_path)


def test_the_agent_hears_the_ceddp_presence_and_asks_with_its_clock(tmp_path: Path) -> None:
    bus = MemoryBus()
    ceddp = MemoryTransport(bus)
    agent = _agent(bus, tmp_path)
    transport = agent.transport
    assert isinstance(transport, MemoryTransport)
    watch = agent.watch_link(transport)
    before = agent.link_signals(transport.delivered)
    assert before.present is None and before.route is None
    token = ceddp.declare_token("arpz/f/ceddp/presence")
    agent.clock_sync.exchange()  # nobody serves the clock: asked, never answered
    after = agent.link_signals(transport.delivered)
    assert after.present is True and after.heard > before.heard
    assert after.asked == before.asked + agent.config.clock.burst
    token.undeclare()
    assert agent.link_signals(transport.delivered).present is False
    transport.reopen()  # the watcher hears the token gone and (absent) not back
    assert agent.link_signals(transport.delivered).present is False
    assert watch.monitor.drops() == []  # not started: nothing decided
    transport.close()
    ceddp.close()


def test_the_summary_is_written_atomically_with_the_counts_and_the_link(tmp_path: Path) -> None:
    bus = MemoryBus()
    agent = _agent(bus, tmp_path)
    transport = agent.transport
    assert isinstance(transport, MemoryTransport)
    watch = agent.watch_link(transport)
    path = tmp_path / "out" / "robot.json"
    summary = RobotSummary(path, agent, watch)
    summary.write(complete=False)
    written = json.loads(path.read_text())
    assert written["complete"] is False and written["robot"] == "r1"
    assert written["incarnation"] == agent.incarnation
    assert set(written["topics"]) == {s.config.name for s in agent.sensors}
    assert all({"produced", "sent", "held_back"} <= set(t) for t in written["topics"].values())
    assert "inbound" in written and written["link"]["drops"] == 0
    assert [p.name for p in path.parent.iterdir()] == ["robot.json"]  # no temporary left
    transport.close()
