"""The built-in specs: seed 001's two studies, and a small grid for the test suite.

Both paper grids run every cell 3 times, so the figures show the spread across repeats; each
adds OPT with only its R applied (``optr``, at every fixed depth) and only its D (``optd``, at
Rmax) to tell which half of OPT carries its effect. docs/experiments.md gives the cell counts
and the expected runtimes; raise ``duration_s`` or ``repeats`` in a copy of the spec for tighter
numbers.
"""

from __future__ import annotations

from arpz.experiment.spec import ExperimentSpec, MissionSpec

PAPER_RMAX = [100.0, 200.0, 500.0, 1000.0]
PAPER_DEPTHS = [1, 5, 10, 100, 1000, 5000]
#: seed 001's configurations (Figures 10, 11 and 16: without optimisation, LC, CC, OPT and the
#: combinations), and OPT with only R or only D applied
PAPER_CONFIGS = ["baseline", "lc", "cc", "optr", "optd", "opt", "lc+opt", "lc+cc+opt"]
PAPER_REPEATS = 3


def paper_machines() -> ExperimentSpec:
    """Figures 10 and 11: Hello latency and loss of machines 1-3 over a bad WiFi link."""
    return ExperimentSpec(
        name="paper-machines",
        description="seed 001 section 3.1, Figures 10-11: the Hello round trip and every "
        "sensor sample of machines 1-3, RELIABLE + KEEP_LAST, over an emulated bad 2.4 GHz link",
        rmax_hz=PAPER_RMAX,
        depths=PAPER_DEPTHS,
        configs=PAPER_CONFIGS,
        networks=["wifi-bad"],
        duration_s=5.0,
        repeats=PAPER_REPEATS,
    )


def paper_simulation() -> ExperimentSpec:
    """Figure 16: the hallway mission of three simulated robots, per Rmax and configuration."""
    return ExperimentSpec(
        name="paper-simulation",
        description="seed 001 section 3.2, Figure 16: the hallway mission (8 LIDAR beams per "
        "robot, planned on the CEDDP), RELIABLE + KEEP_LAST, over an emulated bad 2.4 GHz link",
        rmax_hz=PAPER_RMAX,
        depths=[1, 1000],
        configs=PAPER_CONFIGS,
        networks=["wifi-bad"],
        mission=MissionSpec(world="hallway_small", time_limit_s=60.0),
        repeats=PAPER_REPEATS,
    )


def paper_vs_ros2() -> ExperimentSpec:
    """Figures 10 and 11 with seed 001's own baseline measured beside arpz: the same
    application in rclpy over Fast DDS and on arpz, cells interleaved, in the kernel lab with
    8 % random loss each way (about the proxy grid's wifi-bad: 3 % plus bursts of about 5 %)."""
    return ExperimentSpec(
        name="paper-vs-ros2",
        description="seed 001 section 3.1, Figures 10-11, ROS 2 + Fast DDS (rclpy) and arpz "
        "side by side: machines 1-3, RELIABLE + KEEP_LAST, 8 % kernel-level loss each way",
        rmax_hz=PAPER_RMAX,
        depths=PAPER_DEPTHS,
        configs=["baseline", "opt"],
        networks=["lab:loss-8"],
        middlewares=["arpz", "ros2"],
        duration_s=5.0,
        repeats=PAPER_REPEATS,
    )


def quick() -> ExperimentSpec:
    """A few cells that show both ends in under 3 minutes: next to no loss on a clean link with a
    deep history, loss with depth 1 at a high rate over a lossy one, and OPT."""
    return ExperimentSpec(
        name="quick",
        description="test-suite grid: lan vs wifi-bad, depth 1 vs 1000, baseline vs LC + OPT",
        rmax_hz=[1000.0],
        depths=[1, 1000],
        configs=["baseline", "lc+opt"],
        networks=["lan", "wifi-bad"],
        duration_s=4.0,
        repeats=1,
    )


PRESETS = {
    "paper-machines": paper_machines,
    "paper-simulation": paper_simulation,
    "paper-vs-ros2": paper_vs_ros2,
    "quick": quick,
}
