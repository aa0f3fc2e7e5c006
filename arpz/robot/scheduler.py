"""The robot's periodic jobs on one thread: a heap of due times.

A robot with many sensors (each at its own rate), a Hello probe, a simulated body, a command
watchdog and periodic reports needs no thread per job: one loop sleeps until the earliest job is
due, runs it, and schedules its next run. A job that fell more than a period behind (a slow
driver, an overloaded CPU) is re-aligned instead of bursting to catch up, and the skipped
periods are reported to ``on_late`` with the job.
"""

from __future__ import annotations

import heapq
import threading
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field


@dataclass
class Job:
    due_s: float
    order: int
    period_s: float = field(compare=False)
    run: Callable[[float], None] = field(compare=False)
    name: str = field(compare=False)
    #: runs inside the ``tick()`` context of ``Scheduler.run`` (the robot's sensor jobs, whose
    #: messages are bundled); other jobs run outside it, so that a report or a probe that
    #: waits never holds a tick's sensor messages back
    in_tick: bool = field(default=False, compare=False)

    def __lt__(self, other: Job) -> bool:
        """The heap's order: due time, then the order of creation. Written out, not
        ``dataclass(order=True)``'s, which builds two tuples a comparison: a robot's tick of
        8 topics makes about 60 (``benchmarks/investigations/scheduler_cost.py``: 0.68x a tick,
        issue 17)."""
        return self.due_s < other.due_s or (self.due_s == other.due_s and self.order < other.order)


class Scheduler:
    """Owns the jobs; ``run`` is the robot's scheduler thread."""

    def __init__(self) -> None:
        self._jobs: list[Job] = []

    def every(
        self,
        period_s: float,
        run: Callable[[float], None],
        name: str,
        *,
        first_s: float = 0.0,
        in_tick: bool = False,
    ) -> Job:
        """Run ``run(now_s)`` every ``period_s``, first at ``first_s`` (seconds since start).
        The job returned is the handle to change its period by (a QoS assignment's rate; a float
        assignment, picked up at its next run, so any thread may do it): names are for logs only
        and need not be unique (a sensor may be called "stats")."""
        job = Job(first_s, len(self._jobs), period_s, run, name, in_tick)
        heapq.heappush(self._jobs, job)
        return job

    def stagger(self, now_s: float, fraction: float) -> None:
        """Next run every job ``fraction`` (0..1) of its own period after ``now_s``: robots
        started in the same instant (a load generator's) would otherwise tick, report, probe and
        sync their clocks in the same instant every period, for as long as they run."""
        if not 0.0 <= fraction < 1.0:
            raise ValueError(f"fraction must be in [0, 1), got {fraction}")
        for job in self._jobs:
            job.due_s = now_s + fraction * job.period_s
        heapq.heapify(self._jobs)

    def run(
        self,
        stop: threading.Event,
        clock: Callable[[], float],
        *,
        end_s: float = float("inf"),
        on_late: Callable[[Job, int], None] | None = None,
        tick: Callable[[], AbstractContextManager[object]] | None = None,
    ) -> None:
        """Run the jobs until ``stop`` is set or ``clock()`` reaches ``end_s``. The ``in_tick``
        jobs due at one instant run inside one ``tick()`` context (the robot's
        ``Bundler.collect``: the sensor messages of one tick leave as one Zenoh message); the
        context is left before any other job runs."""
        jobs = self._jobs
        heapq.heapify(jobs)
        while not stop.is_set():
            now_s = clock()
            if now_s >= end_s:
                break
            if jobs and jobs[0].due_s <= now_s:
                self.run_due(now_s, on_late=on_late, tick=tick)
            else:
                next_s = jobs[0].due_s if jobs else float("inf")
                stop.wait(min(next_s - now_s, end_s - now_s, 0.05))

    def run_due(
        self,
        now_s: float,
        *,
        on_late: Callable[[Job, int], None] | None = None,
        tick: Callable[[], AbstractContextManager[object]] | None = None,
    ) -> float:
        """Run the jobs due at ``now_s`` (as ``run`` does, without waiting); the time the next
        one is due (inf with no jobs). For a caller that drives several schedulers from one
        thread (``python -m arpz.perf fleet``'s robots of one process)."""
        jobs = self._jobs
        if not jobs:
            return float("inf")
        if jobs[0].due_s > now_s:
            return jobs[0].due_s
        if tick is None:  # one job at a time, each at its own reading of the clock
            job = jobs[0]
            job.run(now_s)
            self._reschedule(job, now_s, on_late)
            heapq.heapreplace(jobs, job)
            return jobs[0].due_s
        ticking: list[Job] = []
        others: list[Job] = []
        while jobs and jobs[0].due_s <= now_s:
            job = heapq.heappop(jobs)
            (ticking if job.in_tick else others).append(job)
        # the tick's jobs first, in their heap order, all in one context
        if ticking:
            with tick():
                for job in ticking:
                    job.run(now_s)
        for job in others:
            job.run(now_s)
        for job in ticking + others:
            self._reschedule(job, now_s, on_late)
            heapq.heappush(jobs, job)
        return jobs[0].due_s

    @staticmethod
    def _reschedule(job: Job, now_s: float, on_late: Callable[[Job, int], None] | None) -> None:
        job.due_s += job.period_s
        if job.due_s < now_s - job.period_s:
            # re-aligned to a period from now: the periods between this run's due time and
            # the next run are periods without a run (with the re-alignment's fraction)
            if on_late is not None:
                on_late(job, round((now_s - job.due_s) / job.period_s) + 1)
            job.due_s = now_s + job.period_s
