"""One process of the fleet load test: several real ``RobotAgent``s, each with its own Zenoh
client session, as separate robots would have; their periodic jobs run on one thread of the
process (``run_together``), or on a thread each with ``--robot-threads own``.

``python -m arpz.perf fleet-worker --plan PLAN.json --worker I`` (started by ``arpz.perf.fleet``,
not by hand). The worker opens every session and starts every agent (presence, announcement,
matching of its writers), prints ``ready``, and waits for the go file the orchestrator writes
once every worker is ready, so that no robot's traffic overlaps another's start-up; then the
agents run until SIGINT/SIGTERM, shut down cleanly (final reports through the channel, each
waiting for its acknowledgement, all at once) and the worker writes what each agent counted.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from arpz.core.config import RobotConfig, from_dict
from arpz.core.transport import SessionSettings
from arpz.robot.agent import RobotAgent
from arpz.runtime.startup import wait_for_stop
from arpz.transport.zenoh import ZenohTransport

log = logging.getLogger("arpz.perf.fleet")
#: how long a robot waits for its settling burst's replies (``RobotAgent.settle_clock``)
SETTLE_CLOCK_S = 1.0
#: the longest the robots' thread sleeps, and the longest it leaves a robot uncalled
MAX_WAIT_S = 0.05


def _counts(agent: RobotAgent) -> dict[str, Any]:
    counters = agent.counters().values()
    return {
        "produced": sum(c.produced for c in counters),
        "sent": sum(c.sent for c in counters),
        "held_back": sum(c.held_back for c in counters),
        "write_failures": sum(c.write_failures for c in counters),
        "late_ticks": sum(s.late_ticks for s in agent.sensors),
    }


def _parallel(jobs: dict[str, Any], what: str) -> list[str]:
    """Run each callable of ``jobs`` (name -> callable) on its own thread; the errors, named."""
    errors: list[str] = []

    def run(name: str, job: Any) -> None:
        try:
            job()
        except Exception as exc:  # one robot's failure is reported, the others go on
            errors.append(f"{name}: {what} failed: {exc!r}")

    threads = [
        threading.Thread(target=run, args=(n, j), name=f"{what}-{n}", daemon=True)
        for n, j in jobs.items()
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return errors


def run_together(agents: dict[str, RobotAgent], stop: threading.Event, errors: list[str]) -> None:
    """Run the periodic jobs (sensing ticks, reports, probes) of all ``agents`` (name -> agent)
    on this one thread until ``stop``, each robot's at its own times as its ``run`` would. A
    robot whose job raises is reported in ``errors`` and left out; the others go on.

    Why not a thread per robot (``--robot-threads own``): on real hardware each robot has its
    own CPU, but a worker packs a dozen robots into one process and one GIL, and a dozen
    sensing threads waking 100 times a second each queued for the GIL behind one another and
    the channels' threads. With 50 robots x 8 topics x 100 Hz in 4 processes the robots then
    sent half the offered 40 000 samples/s at 1.4 cores; from one thread a worker they sent
    0.96 of it at 1.0-1.2 cores (issue 17; benchmarks/RESULTS.md). Every job is still the real
    agent's: its sensors, local cache, channel writers, bundles and session.

    A robot is called only once its next job is due (by what its last call said, counted from
    just before that call: never late, at worst a few microseconds early): calling each of a
    dozen robots whenever any one was due cost the thread 11 calls for nothing a tick. Counted
    from the start of the pass instead, the robots late in a pass were called a millisecond
    early, found nothing due and woke the thread once more each tick: the fleet's robots sent
    0.95x (three A/B rounds). Every robot's jobs are made at its start, so nothing becomes due
    sooner than it said."""
    running = dict(agents)
    next_due = dict.fromkeys(running, 0.0)  # time.monotonic() of each robot's next due job
    while running and not stop.is_set():
        now = time.monotonic()
        wait_s = MAX_WAIT_S
        for name, agent in list(running.items()):
            due = next_due[name]
            if due > now:
                wait_s = min(wait_s, due - now)
                continue
            called = time.monotonic()  # the pass's "now" is stale after the robots before
            try:
                after = agent.run_due()
            except Exception as exc:
                log.exception("robot %s stopped: a periodic job raised", name)
                errors.append(f"{name}: run failed: {exc!r}")
                del running[name]
                continue
            next_due[name] = called + min(after, MAX_WAIT_S)
            wait_s = min(wait_s, after)
        if wait_s > 0:
            stop.wait(wait_s)


def run_worker(plan_path: Path, index: int, stop: threading.Event) -> dict[str, Any]:
    plan = json.loads(plan_path.read_text(encoding="utf-8"))
    configs = [
        from_dict(raw, RobotConfig, source=f"{plan_path} worker {index}")
        for raw in plan["workers"][index]
    ]
    go_file = Path(plan["go_file"])
    # the robots yield the CPU to the CEDDP: on one host the load generator must not starve
    # the server it measures (real robots have CPUs of their own)
    os.nice(int(plan.get("nice", 0)))
    if plan.get("sched", "normal") == "batch":
        # before any thread starts: the threads created later (Zenoh's, the channels') inherit
        # the calling thread's policy; the niceness set above stays and still weighs their share
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    zenoh_config = plan.get("zenoh_config")
    with ExitStack() as stack:
        agents: dict[str, RobotAgent] = {}
        for config in configs:
            transport = ZenohTransport.open(
                SessionSettings(mode="client", connect=config.connect, config_file=zenoh_config),
                timeout_s=config.connect_timeout_s,
            )
            stack.callback(transport.close)
            agents[config.robot_id] = RobotAgent(config, transport)
        # start (presence, announcement, matching) in parallel: each waits for its readers
        errors = _parallel({name: agent.start for name, agent in agents.items()}, "start")
        print(f"arpz.perf fleet-worker {index}: ready ({len(agents)} robots)", flush=True)
        while not go_file.exists() and not stop.is_set():
            time.sleep(0.01)
        # every robot's clock estimate again, now that the fleet has started and before its
        # load (one robot after another: the exchanges must not queue behind each other)
        unsettled = [n for n, a in agents.items() if not a.settle_clock(SETTLE_CLOCK_S)]
        if unsettled:
            log.warning("clock not settled within %.1f s: %s", SETTLE_CLOCK_S, unsettled)
        started = time.monotonic()
        # each robot's jobs at its own phase of their periods (``--robot-phases``): released
        # together they would run in lockstep, every report of the fleet in the same instant
        phases: dict[str, float] = plan.get("phases") or {}
        for name, agent in agents.items():
            agent.stagger_jobs(phases.get(name, 0.0))
        if plan.get("robot_threads", "shared") == "shared":
            together = (agents, stop, errors)
            threads = [
                threading.Thread(target=run_together, args=together, name="robots", daemon=True)
            ]
        else:
            threads = [
                threading.Thread(target=agent.run, args=(stop,), name=f"robot-{name}", daemon=True)
                for name, agent in agents.items()
            ]
        for thread in threads:
            thread.start()
        scheduling = thread_scheduling(threads[0].native_id)
        # no late ticks to take off as a baseline: the stagger above put every job's next run
        # after the go (before it, the jobs overdue since start-up each counted one late tick)
        wait_for_stop(stop)  # not stop.wait(): a signal may land on any of its threads
        for thread in threads:
            thread.join()
        ran_s = time.monotonic() - started
        # final reports, each waiting (bounded) for the CEDDP's acknowledgement
        errors += _parallel({name: agent.shutdown for name, agent in agents.items()}, "shutdown")
        counts = {name: _counts(agent) for name, agent in agents.items()}
    for error in errors:
        print(f"arpz.perf fleet-worker {index}: {error}", file=sys.stderr, flush=True)
    return {
        "worker": index,
        "ran_s": ran_s,
        "robots": counts,
        "errors": errors,
        "scheduling": scheduling,
    }


def thread_scheduling(tid: int | None) -> str:
    """How the kernel schedules a thread, as the report prints it ("SCHED_BATCH, nice 10"):
    read from the robots' own thread, so the report shows what ran, not what was asked."""
    if tid is None:
        return "unknown"
    try:
        policy = os.sched_getscheduler(tid)
        nice = os.getpriority(os.PRIO_PROCESS, tid)  # a thread id: Linux keeps nice per thread
    except OSError as exc:  # the thread ended already (every robot failed): still a report
        return f"unknown ({exc.strerror})"
    names = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_BATCH: "SCHED_BATCH"}
    return f"{names.get(policy, f'policy {policy}')}, nice {nice}"
