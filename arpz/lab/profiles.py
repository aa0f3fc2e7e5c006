"""The lab's link profiles: what a robot's radio link is like over time, with their numbers in one
place (docs/netem.md, "The kernel lab", lists the same table).

A ``Profile`` is a list of ``Phase``s, each a ``Regime`` from a time on (seconds from the start of
the profile: the moment the fleet is up). ``schedule`` turns a profile into the concrete
``LinkState`` changes the lab applies, drawing the Gilbert-Elliott bursts and the flaps; it is
pure and seeded, so a profile is unit-tested without a kernel.

Names (``parse_profile``): the fixed ones of ``PROFILES`` and the parametrised ``loss-P``
(``loss-P-Q``: P % up, Q % down), ``dead-zone-Ns`` (``dead-zone-Ns-at-Ts``; one way only:
``dead-zone-down-Ns``, ``dead-zone-up-Ns``, with or without ``-at-Ts``), ``rate-R``
(``rate-2mbit``, ``rate-500kbit``), ``roam-at-Ts``, ``flap-Ds-Us`` (down D s, up U s, from
``FLAP_START_S``). From Python: ``loss``, ``dead_zone``, ``rate``, ``roam``, ``flapping``,
``bursty``.
"""

from __future__ import annotations

import random
import re
from dataclasses import dataclass, field, replace
from typing import Literal

#: a profile's clean lead before a dead zone or roaming: the robots' sessions are up and running
LEAD_S = 10.0
#: when ``roam`` moves a robot to the other access point
ROAM_AT_S = 15.0
#: when a flapping link starts flapping
FLAP_START_S = 5.0
#: a Gilbert-Elliott state lasts at least this long (each switch is an nftables transaction)
MIN_DWELL_S = 0.05

#: which way a dead zone drops: ``up`` robot -> access point, ``down`` access point -> robot
Direction = Literal["both", "up", "down"]


def _check_pct(value: float, what: str) -> None:
    if not 0.0 <= value <= 100.0:
        raise ValueError(f"{what} must be 0..100 %, got {value}")


@dataclass(frozen=True)
class GilbertElliott:
    """Bursty loss: the link alternates between Good (the regime's own loss) and Bad
    (``bad_loss_pct`` each way) with exponentially distributed stays of mean ``good_s`` and
    ``bad_s``. Mean loss = (good_s * loss_good + bad_s * bad_loss_pct) / (good_s + bad_s)."""

    good_s: float = 5.0
    bad_s: float = 1.0
    bad_loss_pct: float = 50.0

    def __post_init__(self) -> None:
        if not (self.good_s > 0 and self.bad_s > 0):
            raise ValueError("good_s and bad_s must be > 0")
        _check_pct(self.bad_loss_pct, "bad_loss_pct")


@dataclass(frozen=True)
class Flap:
    """A link that drops everything for ``down_s``, then works for ``up_s``, again and again
    (starting up)."""

    down_s: float = 1.0
    up_s: float = 4.0

    def __post_init__(self) -> None:
        if not (self.down_s > 0 and self.up_s > 0):
            raise ValueError("down_s and up_s must be > 0")


@dataclass(frozen=True)
class LinkState:
    """What the lab applies to one robot's link at one moment."""

    #: random loss robot -> access point and access point -> robot
    loss_up_pct: float = 0.0
    loss_down_pct: float = 0.0
    #: everything dropped both ways (a dead zone, a flap's down time)
    dead: bool = False
    #: tbf bandwidth limit each way (None: none)
    rate_kbit: int | None = None
    #: which access point (bridge, subnet) the robot is on: 0 or 1
    subnet: int = 0

    def __post_init__(self) -> None:
        _check_pct(self.loss_up_pct, "loss_up_pct")
        _check_pct(self.loss_down_pct, "loss_down_pct")
        if self.rate_kbit is not None and self.rate_kbit < 8:
            raise ValueError(f"rate_kbit must be >= 8 (or None), got {self.rate_kbit}")
        if self.subnet not in (0, 1):
            raise ValueError(f"subnet must be 0 or 1, got {self.subnet}")

    def describe(self) -> str:
        parts = []
        if self.dead:
            parts.append("DEAD (all dropped)")
        elif self.loss_up_pct or self.loss_down_pct:
            parts.append(f"loss {self.loss_up_pct:g} % up / {self.loss_down_pct:g} % down")
        if self.rate_kbit is not None:
            parts.append(f"rate {self.rate_kbit} kbit/s")
        parts.append(f"AP {self.subnet}")
        return ", ".join(parts) if parts[:-1] else f"clean, AP {self.subnet}"


CLEAN = LinkState()


@dataclass(frozen=True)
class Regime:
    """A phase's link: a ``LinkState``, optionally with bursts or flaps on top."""

    link: LinkState = CLEAN
    burst: GilbertElliott | None = None
    flap: Flap | None = None

    def __post_init__(self) -> None:
        if self.burst is not None and self.flap is not None:
            raise ValueError("a regime has bursts or flaps, not both")


@dataclass(frozen=True)
class Phase:
    at_s: float
    regime: Regime


@dataclass(frozen=True)
class Profile:
    name: str
    description: str
    phases: tuple[Phase, ...] = field(default=(Phase(0.0, Regime()),))

    def __post_init__(self) -> None:
        if not self.phases or self.phases[0].at_s != 0.0:
            raise ValueError(f"profile {self.name!r}: the first phase starts at 0 s")
        times = [p.at_s for p in self.phases]
        if times != sorted(times) or len(set(times)) != len(times):
            raise ValueError(f"profile {self.name!r}: phases must start at increasing times")


@dataclass(frozen=True)
class Step:
    """``state`` applies from ``at_s`` (seconds from the profile's start); ``cause`` says why."""

    at_s: float
    state: LinkState
    cause: str


def _one(
    name: str, description: str, link: LinkState, burst: GilbertElliott | None = None
) -> Profile:
    return Profile(name, description, (Phase(0.0, Regime(link, burst=burst)),))


# --------------------------------------------------------------------- parametrised profiles


def clean() -> Profile:
    return _one("clean", "no impairment", CLEAN)


def loss(up_pct: float, down_pct: float | None = None) -> Profile:
    down = up_pct if down_pct is None else down_pct
    name = f"loss-{up_pct:g}" if down == up_pct else f"loss-{up_pct:g}-{down:g}"
    return _one(
        name,
        f"random loss {up_pct:g} % up, {down:g} % down",
        LinkState(loss_up_pct=up_pct, loss_down_pct=down),
    )


def dead_zone(seconds: float, at_s: float = LEAD_S, direction: Direction = "both") -> Profile:
    """Everything dropped for ``seconds`` from ``at_s``: both ways, or one way only (``down``:
    what the CEDDP sends the robot, commands and acknowledgements of its data, while what the
    robot sends still arrives; ``up`` the other way)."""
    if not (seconds > 0 and at_s > 0):
        raise ValueError("a dead zone lasts > 0 s and starts after 0 s")
    if direction not in ("both", "up", "down"):
        raise ValueError(f"direction must be both, up or down, got {direction!r}")
    way = "" if direction == "both" else f"{direction}-"
    name = f"dead-zone-{way}{seconds:g}s" + ("" if at_s == LEAD_S else f"-at-{at_s:g}s")
    dead = {
        "both": (LinkState(dead=True), "both ways"),
        "up": (LinkState(loss_up_pct=100.0), "robot -> access point (up)"),
        "down": (LinkState(loss_down_pct=100.0), "access point -> robot (down)"),
    }
    state, what = dead[direction]
    return Profile(
        name,
        f"clean, then everything dropped {what} from {at_s:g} s for {seconds:g} s, then clean",
        (
            Phase(0.0, Regime()),
            Phase(at_s, Regime(state)),
            Phase(at_s + seconds, Regime()),
        ),
    )


def rate(kbit: int) -> Profile:
    return _one(
        f"rate-{format_rate(kbit)}",
        f"tbf bandwidth limit {format_rate(kbit)} each way",
        LinkState(rate_kbit=kbit),
    )


def roam(at_s: float = ROAM_AT_S) -> Profile:
    if not at_s > 0:
        raise ValueError("roaming happens after 0 s")
    return Profile(
        "roam" if at_s == ROAM_AT_S else f"roam-at-{at_s:g}s",
        f"on access point 0, moved at {at_s:g} s to access point 1 (another subnet: new "
        "address, new default route)",
        (Phase(0.0, Regime()), Phase(at_s, Regime(LinkState(subnet=1)))),
    )


def flapping(down_s: float = 1.0, up_s: float = 4.0, at_s: float = FLAP_START_S) -> Profile:
    return Profile(
        f"flap-{down_s:g}s-{up_s:g}s",
        f"clean, then from {at_s:g} s everything dropped for {down_s:g} s every "
        f"{down_s + up_s:g} s",
        (Phase(0.0, Regime()), Phase(at_s, Regime(flap=Flap(down_s=down_s, up_s=up_s)))),
    )


def bursty(
    good_loss_pct: float = 1.0, burst: GilbertElliott = GilbertElliott(), name: str = ""
) -> Profile:
    mean = (burst.good_s * good_loss_pct + burst.bad_s * burst.bad_loss_pct) / (
        burst.good_s + burst.bad_s
    )
    return _one(
        name or f"bursty-{good_loss_pct:g}-{burst.bad_loss_pct:g}",
        f"Gilbert-Elliott: {good_loss_pct:g} % each way in Good (mean {burst.good_s:g} s), "
        f"{burst.bad_loss_pct:g} % in Bad (mean {burst.bad_s:g} s): {mean:.1f} % on average",
        LinkState(loss_up_pct=good_loss_pct, loss_down_pct=good_loss_pct),
        burst=burst,
    )


def format_rate(kbit: int) -> str:
    return f"{kbit // 1000}mbit" if kbit % 1000 == 0 else f"{kbit}kbit"


# --------------------------------------------------------------------- the named profiles


def _named(profile: Profile, name: str, description: str | None = None) -> Profile:
    return replace(profile, name=name, description=description or profile.description)


#: the named profiles: ``python -m arpz lab profiles`` prints them, docs/netem.md lists them
PROFILES: dict[str, Profile] = {
    p.name: p
    for p in (
        clean(),
        _named(loss(1.0), "wifi-good", "a good WiFi link: random loss 1 % each way"),
        _named(loss(15.0), "wifi-bad", "a bad WiFi link: random loss 15 % each way"),
        bursty(1.0, GilbertElliott(good_s=5.0, bad_s=1.0, bad_loss_pct=50.0), "wifi-bursty"),
        dead_zone(12.0),
        roam(),
        _named(rate(2000), "congested-2mbit"),
        _named(flapping(), "flapping"),
    )
}

_LOSS = re.compile(r"^loss-(\d+(?:\.\d+)?)(?:-(\d+(?:\.\d+)?))?$")
_DEAD = re.compile(r"^dead-zone-(?:(up|down)-)?(\d+(?:\.\d+)?)s(?:-at-(\d+(?:\.\d+)?)s)?$")
_RATE = re.compile(r"^rate-(\d+)(kbit|mbit)$")
_ROAM = re.compile(r"^roam-at-(\d+(?:\.\d+)?)s$")
_FLAP = re.compile(r"^flap-(\d+(?:\.\d+)?)s-(\d+(?:\.\d+)?)s$")

PARAMETRISED = (
    "loss-P (P % each way), loss-P-Q (P % up, Q % down), dead-zone-Ns, dead-zone-Ns-at-Ts, "
    "dead-zone-down-Ns(-at-Ts) and dead-zone-up-Ns(-at-Ts) (one way only), "
    "rate-Rkbit / rate-Rmbit, roam-at-Ts, flap-Ds-Us"
)


def parse_profile(text: str) -> Profile:
    """A named profile or a parametrised one; ValueError naming the choices otherwise."""
    text = text.strip()
    if text in PROFILES:
        return PROFILES[text]
    if match := _LOSS.match(text):
        return loss(float(match.group(1)), None if match.group(2) is None else float(match[2]))
    if match := _DEAD.match(text):
        at_s = LEAD_S if match[3] is None else float(match[3])
        direction: Direction = "up" if match[1] == "up" else "down" if match[1] else "both"
        return dead_zone(float(match[2]), at_s, direction)
    if match := _RATE.match(text):
        return rate(int(match.group(1)) * (1000 if match.group(2) == "mbit" else 1))
    if match := _ROAM.match(text):
        return roam(float(match.group(1)))
    if match := _FLAP.match(text):
        return flapping(float(match.group(1)), float(match.group(2)))
    raise ValueError(f"unknown profile {text!r}: one of {', '.join(PROFILES)}, or {PARAMETRISED}")


def parse_assignments(values: list[str], robots: list[str]) -> dict[str, Profile]:
    """``--profile`` values: ``ROBOT=PROFILE`` for one robot, ``PROFILE`` for every robot not
    named; robots named nowhere get ``clean``."""
    default = clean()
    named: dict[str, Profile] = {}
    for value in values:
        robot, sep, text = value.rpartition("=")
        if not sep:
            default = parse_profile(text)
            continue
        if robot not in robots:
            raise ValueError(f"--profile {value!r}: no robot {robot!r} (robots: {robots})")
        named[robot] = parse_profile(text)
    return {robot: named.get(robot, default) for robot in robots}


# --------------------------------------------------------------------- the schedule


def schedule(profile: Profile, end_s: float, rng: random.Random) -> list[Step]:
    """The changes ``profile`` makes from 0 up to ``end_s``: a step wherever the state changes
    (the first at 0 s). Bursts draw their stays from ``rng``."""
    steps: list[Step] = []

    def emit(at_s: float, state: LinkState, cause: str) -> None:
        if not steps or steps[-1].state != state:
            steps.append(Step(at_s, state, cause))

    bounds = [p.at_s for p in profile.phases[1:]] + [end_s]
    for index, (phase, until) in enumerate(zip(profile.phases, bounds, strict=True)):
        if phase.at_s >= end_s:
            break
        regime, where = phase.regime, f"{profile.name} phase {index + 1}"
        if regime.burst is not None:
            burst, t, bad = regime.burst, phase.at_s, False
            bad_state = replace(
                regime.link, loss_up_pct=burst.bad_loss_pct, loss_down_pct=burst.bad_loss_pct
            )
            while t < until:
                emit(
                    t,
                    bad_state if bad else regime.link,
                    f"{where}: burst {'bad' if bad else 'good'}",
                )
                mean = burst.bad_s if bad else burst.good_s
                t += max(MIN_DWELL_S, rng.expovariate(1.0 / mean))
                bad = not bad
        elif regime.flap is not None:
            flap, t, down = regime.flap, phase.at_s, False
            down_state = replace(regime.link, dead=True)
            while t < until:
                emit(
                    t,
                    down_state if down else regime.link,
                    f"{where}: flap {'down' if down else 'up'}",
                )
                t += flap.down_s if down else flap.up_s
                down = not down
        else:
            emit(phase.at_s, regime.link, where)
    return steps
