"""The kernel network lab: the real CEDDP and robots in network namespaces behind an access
point, their radio links impaired by the kernel (nftables loss, dead zones, roaming between two
subnets, tbf bandwidth) on a profile's timeline. Root only (docs/netem.md, "The kernel lab").

```python
from arpz.lab import Lab, LinkState, ProfileRunner, dead_zone, spans

with Lab.create(2) as lab:  # robot1, robot2; everything removed on the way out
    ceddp = lab.spawn("ceddp", lab.ceddp_namespace, ["-m", "arpz.ceddp", ...], workdir)
    robot = lab.spawn("robot1", lab.robot("robot1").namespace, ["-m", "arpz.robot", ...], workdir)
    lab.apply("robot2", LinkState(loss_up_pct=5, loss_down_pct=5))  # now
    runner = ProfileRunner(lab, {"robot1": dead_zone(12)})  # over time
    runner.start()
    ...
    runner.stop()
    print(spans(lab.timeline.entries, "robot1", lambda s: s.dead))  # [(10.0, 22.0)]
```
"""

from arpz.lab.fleet import LabRunOptions, LabRunResult, lab_spec, run_fleet_in_lab, run_lab
from arpz.lab.impair import ProfileRunner
from arpz.lab.names import LabError, LabInterrupted, LabUnavailable
from arpz.lab.net import (
    Lab,
    LinkCounters,
    RobotLink,
    check_available,
    interrupt_on_signals,
    missing,
)
from arpz.lab.profiles import (
    PROFILES,
    Flap,
    GilbertElliott,
    LinkState,
    Profile,
    bursty,
    dead_zone,
    flapping,
    loss,
    parse_profile,
    rate,
    roam,
)
from arpz.lab.timeline import TIMELINE_FILE, Timeline, load, spans

__all__ = [
    "PROFILES",
    "TIMELINE_FILE",
    "Flap",
    "GilbertElliott",
    "Lab",
    "LabError",
    "LabInterrupted",
    "LabRunOptions",
    "LabRunResult",
    "LabUnavailable",
    "LinkCounters",
    "LinkState",
    "Profile",
    "ProfileRunner",
    "RobotLink",
    "Timeline",
    "bursty",
    "check_available",
    "dead_zone",
    "flapping",
    "interrupt_on_signals",
    "lab_spec",
    "load",
    "loss",
    "missing",
    "parse_profile",
    "rate",
    "roam",
    "run_fleet_in_lab",
    "run_lab",
    "spans",
]
