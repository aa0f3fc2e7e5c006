"""What an experiment is: a grid of cells over Rmax, DEPTH and configuration, a fleet, and a
network profile per robot link, loaded from TOML into msgspec Structs.

The spec is data, not code, so that anyone can rerun or extend seed 001's study by editing a
file; unknown fields are errors naming the field (a typo must not silently shrink a grid).
"""

from __future__ import annotations

import itertools
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from arpz.core.errors import ArpzError

#: the features a configuration may combine: seed 001's LC, CC and OPT, and OPT with only one of
#: its two outputs applied (``optr``: the optimiser's R at the cell's fixed depth; ``optd``: the
#: optimiser's D at Rmax), to tell which of the two carries OPT's effect
FEATURES: tuple[str, ...] = ("lc", "cc", "opt", "optr", "optd")
#: the QoS balancing variants: a configuration has at most one
OPT_VARIANTS: tuple[str, ...] = ("opt", "optr", "optd")
#: the depth label of cells whose DEPTH comes from the QoS optimiser: Opt(D) of Table 2
OPT_DEPTH = "opt"
#: a network named ``lab:PROFILE`` runs the cell in the kernel lab (arpz.lab, root only) with
#: that lab profile on every robot's link, instead of behind ``arpz.netem`` proxies
LAB_PREFIX = "lab:"
#: the Zenoh links a lab cell's robots may use (``lab_link``)
LAB_LINKS = ("tcp", "udp", "tls", "quic")
#: the middlewares a cell can run: arpz, or seed 001's own application in rclpy over the ROS 2
#: RMW installed (arpz.experiment.ros2; Fast DDS by default)
MIDDLEWARES = ("arpz", "ros2")
#: the features ROS 2 cells apply: the paper's OPT as ROS 2 applies it (R and D computed
#: offline and configured for the run) and its halves; LC and CC are arpz features, so a
#: configuration with them runs on arpz only
ROS2_FEATURES = ("opt", "optr", "optd")


def runs_on(middleware: str, config: str) -> bool:
    """Whether ``config`` (normalised) has cells on ``middleware``: arpz runs every one, ROS 2
    baseline and the OPT variants only (not LC or CC, which are arpz's)."""
    if middleware == "arpz" or config == "baseline":
        return True
    return all(part in ROS2_FEATURES for part in config.split("+"))


def lab_profile_name(network: str) -> str | None:
    """The lab profile of a ``lab:PROFILE`` network, None for a proxy (arpz.netem) network."""
    return network[len(LAB_PREFIX) :] if network.startswith(LAB_PREFIX) else None


def _check_lab_profile(name: str) -> None:
    # imported here: arpz.lab brings pyroute2 (the server extra), needed by lab cells only
    from arpz.lab.profiles import parse_profile

    try:
        parse_profile(name)
    except ValueError as exc:
        raise ValueError(f"network 'lab:{name}': {exc}") from None


class SpecError(ArpzError, ValueError):
    """A spec that cannot be run; ``str()`` names the source, the field and how to fix it."""


class NetworkProfile(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """One robot's link, emulated by ``arpz.netem`` (both directions impaired alike)."""

    description: str = ""
    loss_pct: float = 0.0
    #: Gilbert-Elliott bursts: Good -> Bad per datagram, Bad -> Good (0 = no bursts)
    burst_p: float = 0.0
    burst_r: float = 0.0
    delay_ms: float = 0.0
    #: +/- uniform jitter; it reorders datagrams, and Zenoh drops a frame older than one it has
    #: seen on a best-effort UDP link, so jitter adds loss (none of the built-in profiles use it)
    jitter_ms: float = 0.0
    #: 0 = unlimited
    rate_kbps: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss_pct <= 100.0:
            raise ValueError(f"loss_pct must be within [0, 100], got {self.loss_pct}")
        for name in ("burst_p", "burst_r"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be within [0, 1], got {getattr(self, name)}")
        if self.burst_p > 0 and self.burst_r <= 0:
            raise ValueError("burst_r must be > 0 when burst_p > 0 (bursts must end)")
        for name in ("delay_ms", "jitter_ms", "rate_kbps"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    @property
    def lossy(self) -> bool:
        return self.loss_pct > 0 or self.burst_p > 0


#: built-in profiles; a spec's [profiles] table may add or override
PROFILES: dict[str, NetworkProfile] = {
    "lan": NetworkProfile(description="loopback through the proxy, no impairment"),
    "wifi-good": NetworkProfile(
        description="a good 2.4 GHz link: 1 % loss, 2 ms, 54 Mb/s",
        loss_pct=1.0,
        delay_ms=2.0,
        rate_kbps=54_000.0,
    ),
    "wifi-bad": NetworkProfile(
        description="a bad 2.4 GHz link: 3 % random loss plus bursts (about 5 % more, "
        "mean burst 4 datagrams), 5 ms, 54 Mb/s",
        loss_pct=3.0,
        burst_p=0.013,
        burst_r=0.25,
        delay_ms=5.0,
        rate_kbps=54_000.0,
    ),
}


class MissionSpec(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Run seed 001 section 3.2's hallway mission in every cell instead of the sensor fleet."""

    world: str = "hallway_small"
    time_limit_s: float = 60.0
    max_age_s: float = 0.3

    def __post_init__(self) -> None:
        if not self.time_limit_s > 0 or not self.max_age_s > 0:
            raise ValueError("time_limit_s and max_age_s must be > 0")


class ExperimentSpec(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """The grid, the fleet and the links; see docs/experiments.md for every field."""

    name: str
    description: str = ""
    rmax_hz: list[float]
    #: fixed KEEP_LAST depths of the configurations whose depth is not the optimiser's (all but
    #: opt and optd, which run at Opt(D) only)
    depths: list[int]
    #: "baseline", or features joined by "+": "lc", "cc", "opt", "optr", "optd", "lc+opt" ...
    configs: list[str]
    #: network profile names (built-in or from [profiles]); every cell runs on each
    networks: list[str] = msgspec.field(default_factory=lambda: ["wifi-bad"])
    #: per-robot override of the cell's network (e.g. one robot on a worse link); in a lab cell
    #: the override must be a lab profile too
    robot_networks: dict[str, str] = msgspec.field(default_factory=dict)
    #: the robots' Zenoh link in ``lab:`` cells (tls and quic with the fleet's mutual TLS)
    lab_link: str = "udp"
    profiles: dict[str, NetworkProfile] = msgspec.field(default_factory=dict)
    repeats: int = 1
    #: seconds of measurement per cell (the sensor fleet; a mission runs to its verdict)
    duration_s: float = 10.0
    #: seed 001's machines 1-3 (section 3.1); robot i gets presets[i-1]
    presets: list[str] = msgspec.field(default_factory=lambda: ["machine1", "machine2", "machine3"])
    hello_rate_hz: float = 10.0
    #: the Hello goes robot1 -> CEDDP -> relay -> CEDDP -> robot1 (seed 001 Fig. 9)
    hello_relay: str = "robot3"
    #: history kept by the local cache for robots when LC is on: see arpz.core.config
    local_cache_max_silence_s: float = 1.0
    rmin_hz: float = 1.0
    dmax: int = 5000
    mission: MissionSpec | None = None
    #: keys of arpz.core.config's TrafficQos set in the CEDDP's and every robot's config, to compare
    #: the fleet's traffic profiles (e.g. ``plain_downlink = true``, or ``[traffic.command_qos]``)
    traffic: dict[str, Any] = msgspec.field(default_factory=dict)
    seed: int = 1
    #: which middlewares run the grid's cells: "arpz", "ros2" (seed 001's application in rclpy
    #: over the RMW installed, lab networks only); ROS 2 gets only the configurations it
    #: applies (baseline, opt, optr, optd: see ``runs_on``), the cells of both interleaved
    middlewares: list[str] = msgspec.field(default_factory=lambda: ["arpz"])

    def __post_init__(self) -> None:
        if not self.rmax_hz or any(not r > 0 for r in self.rmax_hz):
            raise ValueError("rmax_hz must list rates > 0, e.g. [100, 200, 500, 1000]")
        if any(d < 1 for d in self.depths):
            raise ValueError("depths must be >= 1 (KEEP_LAST holds at least one sample)")
        if not self.configs:
            raise ValueError('configs must list at least one, e.g. ["baseline", "lc+opt"]')
        for config in self.configs:
            normalise_config(config)
        if any(not opt_depth(c) for c in self.configs) and not self.depths:
            raise ValueError(
                "configurations whose depth is not the optimiser's (all but opt and optd) need "
                "at least one fixed depth"
            )
        if self.repeats < 1:
            raise ValueError(f"repeats must be >= 1, got {self.repeats}")
        if not self.duration_s > 0 or not self.hello_rate_hz > 0:
            raise ValueError("duration_s and hello_rate_hz must be > 0")
        if not self.presets:
            raise ValueError("presets must list one preset per robot (machine1..3)")
        known = set(PROFILES) | set(self.profiles)
        if self.lab_link not in LAB_LINKS:
            raise ValueError(
                f"lab_link must be one of {', '.join(LAB_LINKS)}, got {self.lab_link!r}"
            )
        for net in [*self.networks, *self.robot_networks.values()]:
            lab = lab_profile_name(net)
            if lab is not None:
                _check_lab_profile(lab)
                continue
            if net not in known:
                raise ValueError(
                    f"unknown network profile {net!r}: use one of {', '.join(sorted(known))} "
                    "or define it under [profiles.NAME]"
                )
        if not self.networks:
            raise ValueError('networks must list at least one profile, e.g. ["wifi-bad"]')
        self._check_middlewares()

    def _check_middlewares(self) -> None:
        if not self.middlewares:
            raise ValueError('middlewares must list at least one, e.g. ["arpz", "ros2"]')
        for middleware in self.middlewares:
            if middleware not in MIDDLEWARES:
                raise ValueError(
                    f"unknown middleware {middleware!r}: use {' or '.join(MIDDLEWARES)}"
                )
        if len(set(self.middlewares)) != len(self.middlewares):
            raise ValueError(f"middlewares lists one twice: {self.middlewares}")
        if "ros2" not in self.middlewares:
            return
        proxied = [
            n for n in [*self.networks, *self.robot_networks.values()] if not lab_profile_name(n)
        ]
        if proxied:
            raise ValueError(
                f"ROS 2 cells run in the kernel lab only: network {proxied[0]!r} is a user-space "
                "UDP proxy, which DDS's discovery and its several ports per participant cannot "
                'cross; use a "lab:PROFILE" network (e.g. "lab:loss-8") or drop "ros2"'
            )
        if self.mission is not None:
            raise ValueError("ROS 2 cells run the sensor fleet (Figures 10-11), not the mission")
        if not any(runs_on("ros2", normalise_config(c)) for c in self.configs):
            raise ValueError(
                f"none of the configs {self.configs} runs on ros2 (LC and CC are arpz "
                "features): add baseline, opt, optr or optd"
            )

    def middleware_configs(self) -> dict[str, list[str]]:
        """The configurations each middleware runs (ROS 2: baseline and the OPT variants)."""
        return {
            middleware: [c for c in map(normalise_config, self.configs) if runs_on(middleware, c)]
            for middleware in self.middlewares
        }

    def profile(self, name: str) -> NetworkProfile:
        return self.profiles.get(name) or PROFILES[name]

    def robot_network(self, cell: Cell, robot: str) -> str:
        """The network of ``robot`` in ``cell``: its override, else the cell's."""
        return self.robot_networks.get(robot, cell.network)

    @property
    def robot_names(self) -> list[str]:
        return [f"robot{i}" for i in range(1, (3 if self.mission else len(self.presets)) + 1)]

    def cells(self) -> list[Cell]:
        """Every cell in run order: Rmax outermost so a partial run covers whole figures; the
        middlewares innermost, so both run each point of the grid under the same host load."""
        out = []
        for rmax, network, config in itertools.product(self.rmax_hz, self.networks, self.configs):
            name = normalise_config(config)
            depths: list[int | str] = [OPT_DEPTH] if opt_depth(name) else list(self.depths)
            for depth in depths:
                for repeat in range(1, self.repeats + 1):
                    for middleware in self.middlewares:
                        if runs_on(middleware, name):
                            out.append(Cell(float(rmax), depth, name, repeat, network, middleware))
        return out


@dataclass(frozen=True)
class Cell:
    """One run: a point of the grid and its repeat number."""

    rmax_hz: float
    depth: int | str
    config: str
    repeat: int
    network: str
    middleware: str = "arpz"

    @property
    def key(self) -> tuple[str, str, str, str, str, str]:
        """How results.csv rows are matched to cells (as the CSV strings them)."""
        return (
            format_rate(self.rmax_hz),
            str(self.depth),
            self.config,
            str(self.repeat),
            self.network,
            self.middleware,
        )

    @property
    def label(self) -> str:
        return (
            f"Rmax {format_rate(self.rmax_hz)} Hz, depth {self.depth}, {self.config}, "
            f"{self.network}, repeat {self.repeat}, {self.middleware}"
        )

    @property
    def slug(self) -> str:
        # arpz's cells keep the slug they had before middlewares (kept runs/ still match)
        prefix = "" if self.middleware == "arpz" else f"{self.middleware}_"
        return (
            f"{prefix}r{format_rate(self.rmax_hz)}_d{self.depth}_{self.config.replace('+', '-')}_"
            f"{self.network.replace(':', '-')}_{self.repeat}"
        )


def format_rate(rate: float) -> str:
    return f"{rate:g}"


def normalise_config(config: str) -> str:
    """ "opt+LC" -> "lc+opt": features lower-cased, de-duplicated and in a fixed order."""
    text = config.strip().lower()
    if text in ("baseline", "none", ""):
        return "baseline"
    parts = [p.strip() for p in text.split("+")]
    unknown = [p for p in parts if p not in FEATURES]
    if unknown:
        raise ValueError(
            f"unknown configuration feature {unknown[0]!r} in {config!r}: use 'baseline' or "
            f"features {', '.join(FEATURES)} joined by '+', e.g. 'lc+opt'"
        )
    variants = [v for v in OPT_VARIANTS if v in parts]
    if len(variants) > 1:
        raise ValueError(
            f"{config!r} combines {' and '.join(variants)}: a configuration applies the "
            "optimiser's R and D (opt), only its R (optr) or only its D (optd), not several"
        )
    return "+".join(f for f in FEATURES if f in parts)


def has_feature(config: str, feature: str) -> bool:
    return feature in config.split("+")


def has_opt(config: str) -> bool:
    """The CEDDP runs the live optimiser and assigns R and D (seed 001's OPT)."""
    return has_feature(config, "opt")


def opt_rate(config: str) -> bool:
    """The robots publish at the optimiser's R (opt, optr), not at Rmax."""
    return has_feature(config, "opt") or has_feature(config, "optr")


def opt_depth(config: str) -> bool:
    """The KEEP_LAST depth is the optimiser's D (opt, optd): the cell's depth is Opt(D)."""
    return has_feature(config, "opt") or has_feature(config, "optd")


#: how figures and tables name the features
_LABELS = {"lc": "LC", "cc": "CC", "opt": "OPT", "optr": "OPT R-only", "optd": "OPT D-only"}


def config_label(config: str) -> str:
    """The paper's names: "without optimisation", "LC", "LC + OPT" ... and "OPT R-only"."""
    if config == "baseline":
        return "no opt."
    return " + ".join(_LABELS.get(p, p.upper()) for p in config.split("+"))


def spec_from_dict(raw: dict[str, Any], *, source: str) -> ExperimentSpec:
    try:
        return msgspec.convert(raw, ExperimentSpec)
    except msgspec.ValidationError as exc:
        text = str(exc)
        if " - at `$" in text:
            message, _, where = text.rpartition(" - at `$")
            text = f"field '{where.rstrip('`').lstrip('.')}': {message}"
        raise SpecError(f"{source}: {text}") from None


def load_spec(path: str | Path) -> ExperimentSpec:
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SpecError(f"{path}: file not found (give a spec file or a preset name)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(f"{path}: cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML: {exc}") from None
    return spec_from_dict(raw, source=str(path))
