"""Seed 001's fleet-wide QoS against the per-topic closed loop, over emulated links (issue 20).

For each link profile (``lan``, ``wifi-good``, ``wifi-bad`` of arpz.experiment, and ``degrade``:
wifi-good for the first half of the run, wifi-bad for the second) and each QoS mode, a real
CEDDP and two robots (seed 001's machine 1 sensors) run through one ``arpz.netem`` proxy:

- ``fleet``: ``[qos] mode = "fleet"``: seed 001's problem (6), one R and D for every topic;
- ``per_topic``: ``[qos] mode = "per_topic"``: each topic's rate by its measured change rate,
  each robot link measured from the channel's counters, the depth the larger of eq. 5's and the
  loss-aware one ("max"), re-solved when the measurements move past the hysteresis.

Both at the same Rmax, so at the same total rate budget (C = A Rmax - N Rmin samples/s). From
the CEDDP's summary: sensor-sample loss (lost / (received + lost)), staleness (how long the
CEDDP held a value other than the robot's latest reading, once per change) and latency (robot
stamp to ingest), per topic; the tables give the worst topic's p99 and the mean of the topics'
p99 weighted by the changes they delivered.

    python benchmarks/qos_per_topic.py --duration 20

The target of the issue: lower loss and lower p99 staleness on every profile. ``--json FILE``
writes every figure. Exit code 0 whatever the result (the figures are the point).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from arpz.experiment.runner import impairments  # noqa: E402
from arpz.experiment.spec import PROFILES  # noqa: E402
from tests.integration.fleet import ceddp, robots, settle, udp_link, write_robot  # noqa: E402
from tests.support import wait_until  # noqa: E402

PROFILE_NAMES = ("lan", "wifi-good", "wifi-bad", "degrade")
MODES = ("fleet", "per_topic")
ROBOTS = ("robot1", "robot2")


def _qos(mode: str, rmax_hz: float) -> str:
    depth = "paper" if mode == "fleet" else "max"
    return (
        f'[qos]\nenabled = true\nmode = "{mode}"\nrmax_hz = {rmax_hz}\n'
        f'depth_policy = "{depth}"\nmeasure_samples = 200\n'
    )


def run_cell(tmp: Path, profile: str, mode: str, *, duration_s: float, rmax_hz: float) -> dict:
    """One CEDDP and two robots over one emulated link; returns the summary's figures."""
    link = udp_link()
    with ceddp(tmp, extra=_qos(mode, rmax_hz), also_listen=(link.ceddp_endpoint,)) as (server, _):
        link.proxy.start()
        try:
            configs = [
                write_robot(tmp, robot, link.robot_endpoint, preset="machine1") for robot in ROBOTS
            ]
            with robots(tmp, configs) as procs:
                for robot in ROBOTS:
                    wait_until(lambda r=robot: f"robot {r} joined" in server.output(), what=robot)
                if profile == "degrade":
                    link.impair(impairments(PROFILES["wifi-good"]))
                    settle(duration_s / 2)
                    link.impair(impairments(PROFILES["wifi-bad"]))
                    settle(duration_s / 2)
                else:
                    if profile != "lan":
                        link.impair(impairments(PROFILES[profile]))
                    settle(duration_s)
                for proc in procs:
                    proc.interrupt(timeout_s=30)
            server.interrupt()
        finally:
            link.proxy.stop()
    summary = json.loads((tmp / "summary.json").read_text())
    return figures(summary)


def figures(summary: dict[str, Any]) -> dict[str, Any]:
    received = lost = 0
    p99s: list[tuple[float, int]] = []
    latency_p99: list[float] = []
    for robot in ROBOTS:
        for name, t in summary["robots"][robot]["topics"].items():
            if name == "hello":
                continue
            received += t["received"]
            lost += t["lost"]
            if t["staleness_ms_p99"] is not None:
                p99s.append((t["staleness_ms_p99"], t["received"]))
            if t["latency_ms_p99"] is not None:
                latency_p99.append(t["latency_ms_p99"])
    weight = sum(n for _, n in p99s) or 1
    qos = summary["qos"] or {}
    return {
        "received": received,
        "lost": lost,
        "loss_pct": 100.0 * lost / (received + lost) if received + lost else 0.0,
        "staleness_ms_p99_worst": max((p for p, _ in p99s), default=None),
        "staleness_ms_p99_weighted": sum(p * n for p, n in p99s) / weight if p99s else None,
        "latency_ms_p99_worst": max(latency_p99, default=None),
        "epochs": len(qos.get("assignments", [])),
        "measured_epochs": len((qos.get("links") or {}).get("measured_changes", [])),
        "links": (qos.get("links") or {}).get("in_force", {}),
    }


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per cell")
    parser.add_argument("--rmax", type=float, default=100.0, help="Rmax of both modes, Hz")
    parser.add_argument("--profiles", default=",".join(PROFILE_NAMES))
    parser.add_argument("--json", type=Path, help="write every figure here")
    args = parser.parse_args()
    started = time.monotonic()
    results: dict[str, dict[str, Any]] = {}
    for profile in args.profiles.split(","):
        for mode in MODES:
            print(f"{profile} / {mode}: {args.duration:.0f} s ...", flush=True)
            with tempfile.TemporaryDirectory() as tmp:
                results.setdefault(profile, {})[mode] = run_cell(
                    Path(tmp), profile, mode, duration_s=args.duration, rmax_hz=args.rmax
                )
    print(
        f"\n{'profile':<10} {'mode':<10} {'received':>8} {'loss %':>7} {'stale p99 worst':>15} "
        f"{'stale p99 wtd':>13} {'lat p99 worst':>13} {'epochs':>6}"
    )
    verdicts = []
    for profile, by_mode in results.items():
        for mode, f in by_mode.items():
            print(
                f"{profile:<10} {mode:<10} {f['received']:>8} {f['loss_pct']:>7.3f} "
                f"{_fmt(f['staleness_ms_p99_worst']):>15} "
                f"{_fmt(f['staleness_ms_p99_weighted']):>13} "
                f"{_fmt(f['latency_ms_p99_worst']):>13} {f['epochs']:>6}"
            )
        fleet, ours = by_mode["fleet"], by_mode["per_topic"]
        lower_loss = ours["loss_pct"] < fleet["loss_pct"] or (
            ours["loss_pct"] == fleet["loss_pct"] == 0
        )
        lower_stale = (ours["staleness_ms_p99_weighted"] or 0) < (
            fleet["staleness_ms_p99_weighted"] or 0
        )
        verdicts.append(
            f"{profile}: loss {'lower or both 0' if lower_loss else 'NOT lower'}, "
            f"weighted p99 staleness {'lower' if lower_stale else 'NOT lower'}"
        )
    print("\n" + "\n".join(verdicts))
    print(f"({time.monotonic() - started:.0f} s)")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
