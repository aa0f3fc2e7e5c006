"""The robot's scheduler: jobs are addressed by the handle ``every`` returns, never by name (a
sensor may be called "stats" like the stats job), and a late job is reported as itself."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

import pytest

from arpz.robot.scheduler import Job, Scheduler


class StepClock:
    """Seconds since start, a microsecond further at every reading; ``stop`` waits on it, so
    the scheduler's sleeps take no real time."""

    def __init__(self) -> None:
        self.now_s = 0.0
        clock = self

        class Stop(threading.Event):
            def wait(self, timeout: float | None = None) -> bool:
                clock.now_s += timeout or 0.0
                return self.is_set()

        self.stop = Stop()

    def __call__(self) -> float:
        self.now_s += 1e-6
        return self.now_s


def test_jobs_of_the_same_name_keep_their_own_periods() -> None:
    scheduler = Scheduler()
    runs = {"sensor": 0, "report": 0}

    def sensor(_now: float) -> None:
        runs["sensor"] += 1

    def report(_now: float) -> None:
        runs["report"] += 1

    fast = scheduler.every(0.01, sensor, "stats")  # a sensor named like the stats job
    scheduler.every(0.1, report, "stats", first_s=0.1)
    fast.period_s = 0.02  # a QoS assignment retunes the sensor through its handle
    clock = StepClock()
    scheduler.run(clock.stop, clock, end_s=1.0)
    assert 45 <= runs["sensor"] <= 51, runs  # every 20 ms for 1 s
    assert 9 <= runs["report"] <= 10, runs  # the other "stats" still every 100 ms


def test_the_job_that_fell_behind_is_reported_as_itself_and_realigned() -> None:
    """Two jobs of one name; one blocks for half a second, so the other falls five periods
    behind: that one is reported (by its handle, not its name) and re-aligned, not burst."""
    scheduler = Scheduler()
    clock = StepClock()
    late: list[tuple[Job, int]] = []
    runs = [0]

    def slow(_now: float) -> None:
        clock.now_s += 0.5  # a driver that blocked for half a second

    def counted(_now: float) -> None:
        runs[0] += 1

    scheduler.every(1.0, slow, "pir")
    other = scheduler.every(0.1, counted, "pir")
    scheduler.run(clock.stop, clock, end_s=1.0, on_late=lambda j, n: late.append((j, n)))
    assert late and all(job is other and n >= 3 for job, n in late), late
    assert runs[0] <= 7, runs  # re-aligned: about 0.5 s of periods, not the 5 it missed as well


def test_jobs_due_at_one_instant_share_one_tick() -> None:
    """The robot bundles what one tick sends: two 100 Hz sensors run inside the same ``tick``
    context, a 50 Hz one joins every other tick, and a report due at the same instant runs
    outside it (a report that waits must never hold the sensors' messages back)."""
    scheduler = Scheduler()
    clock = StepClock()
    ticks: list[list[str]] = []
    current: list[str] = []
    inside = [False]

    @contextlib.contextmanager
    def tick() -> Iterator[None]:
        current.clear()
        inside[0] = True
        yield
        inside[0] = False
        ticks.append(list(current))

    for name, period in (("imu", 0.01), ("gps", 0.01), ("pir", 0.02)):
        scheduler.every(period, lambda _now, n=name: current.append(n), name, in_tick=True)
    report_inside: list[bool] = []
    scheduler.every(0.02, lambda _now: report_inside.append(inside[0]), "stats")
    scheduler.run(clock.stop, clock, end_s=0.1, tick=tick)
    expected = [{"imu", "gps", "pir"}, {"imu", "gps"}] * 5
    assert [set(t) for t in ticks] == expected[: len(ticks)] and len(ticks) >= 9, ticks
    assert len(report_inside) >= 4 and not any(report_inside)


def test_run_due_runs_what_is_due_and_says_when_the_next_is() -> None:
    """Several schedulers driven from one thread (the fleet's robots of one process): each runs
    only its own due jobs, at its own times, and says when it wants the thread again."""
    a, b = Scheduler(), Scheduler()
    runs: list[tuple[str, float]] = []
    a.every(0.01, lambda now: runs.append(("a", now)), "a")
    b.every(0.025, lambda now: runs.append(("b", now)), "b", first_s=0.005)
    assert a.run_due(0.0) == 0.01 and runs == [("a", 0.0)]
    assert b.run_due(0.0) == 0.005 and runs == [("a", 0.0)]  # not due yet: nothing ran
    assert b.run_due(0.005) == pytest.approx(0.03) and runs[-1] == ("b", 0.005)
    assert a.run_due(0.012) == pytest.approx(0.02) and runs[-1] == ("a", 0.012)
    assert Scheduler().run_due(1.0) == float("inf")


def test_stagger_puts_every_job_at_its_fraction_of_its_own_period() -> None:
    scheduler = Scheduler()
    runs: list[tuple[str, float]] = []
    fast = scheduler.every(0.01, lambda now: runs.append(("fast", now)), "tick")
    slow = scheduler.every(1.0, lambda now: runs.append(("slow", now)), "stats")
    scheduler.stagger(5.0, 0.25)
    assert (fast.due_s, slow.due_s) == (5.0025, 5.25)
    # nothing is due before the fast job's phase, and neither job counts as late
    late: list[tuple[Job, int]] = []
    assert scheduler.run_due(5.002, on_late=lambda job, n: late.append((job, n))) == 5.0025
    assert runs == []
    scheduler.run_due(5.0025, on_late=lambda job, n: late.append((job, n)))
    assert runs == [("fast", 5.0025)] and late == []
    with pytest.raises(ValueError, match="fraction"):
        scheduler.stagger(0.0, 1.0)


def test_runs_and_late_ticks_add_up_to_the_periods_that_passed() -> None:
    """What a late robot did not sense is counted: the periods a stalled job skipped are its
    late ticks, so its runs + late ticks = the periods that passed. The fleet's load generator
    reads its shortfall from this (issue 17: it counted about half of what a stalled robot
    skipped, one period too few per stall)."""
    scheduler = Scheduler()
    clock = StepClock()
    late = [0]
    runs = [0]
    stalls = iter([0.025, 0.0, 0.047, 0.0, 0.0, 0.013, 0.101] * 40)

    def stalling(_now: float) -> None:
        clock.now_s += next(stalls, 0.0)  # the thread held up (the GIL, the CPU)

    def sensor(_now: float) -> None:
        runs[0] += 1

    def count(job: Job, ticks: int) -> None:
        if job is imu:
            late[0] += ticks

    scheduler.every(0.05, stalling, "body")
    imu = scheduler.every(0.01, sensor, "imu")
    scheduler.run(clock.stop, clock, end_s=10.0, on_late=count)
    assert late[0] > 100, late
    assert abs(runs[0] + late[0] - 1000) <= 3, (runs[0], late[0])  # 10 s of 10 ms periods


def test_due_jobs_run_by_due_time_then_creation_order_the_tick_s_first() -> None:
    """The heap's order (``Job.__lt__``): the earlier due time first, and among jobs due at the
    same time the one created first; the tick's jobs before the others, each group in that
    order."""
    scheduler = Scheduler()
    ran: list[str] = []
    for name, first_s, in_tick in (
        ("report", 0.0, False),
        ("imu", 0.002, True),
        ("lidar", 0.001, True),
        ("gps", 0.001, True),
        ("probe", 0.001, False),
    ):
        scheduler.every(
            1.0, lambda _now, n=name: ran.append(n), name, first_s=first_s, in_tick=in_tick
        )
    scheduler.run_due(0.002, tick=contextlib.nullcontext)
    assert ran == ["lidar", "gps", "imu", "report", "probe"]
    a = Job(1.0, 0, 1.0, lambda _now: None, "a")
    b = Job(1.0, 1, 1.0, lambda _now: None, "b")
    c = Job(0.5, 2, 1.0, lambda _now: None, "c")
    assert a < b and not b < a and c < a and not a < c and not a < a
