"""The model file of seed 002: computers, links, nodes with settings, messages.

A model file is JSON or TOML (chosen by the file suffix) decoded into frozen msgspec Structs that
forbid unknown fields, so a typo names the field instead of being ignored. ``validate`` then
checks what a type cannot: names that refer to nothing, negative or non-finite numbers, a
coresidence group whose members cannot share any computer. Every problem is reported at once,
each with where it is, so a user fixes a file in one pass. docs/configure.md documents the fields.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import msgspec
import tomli_w

from arpz.configure.regression import FitChoice, FitError, expand, fit, parameter_curves
from arpz.core.errors import ArpzError


class ModelError(ArpzError, ValueError):
    """A model file that cannot be used; the message names the file and every problem found."""


class Setting(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One characterised setting: CPU in % of the baseline computer, performance as quantified."""

    cpu: float
    performance: float
    #: the setting used by Problem 2 (settings are given there, only placement is decided)
    fixed: bool = False
    #: expected message frequency at this setting, for eq. 10 (P_measured = P F_measured/F_expected)
    frequency_hz: float | None = None
    #: the parameter value that produces this setting (particles, Hz, goals): with a continuum,
    #: CPU and performance are also fitted against it (Fig. 3) and a solution reports it
    parameter: float | None = None
    #: what the node sends at this setting (Table I's BW column), in the unit of the links; a
    #: message without its own bandwidth carries its source's
    bandwidth: float | None = None


class Continuum(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    fit: FitChoice = "best"
    step: int = 1
    #: the curves of CPU and performance against the settings' ``parameter`` (Fig. 3)
    parameter_fit: FitChoice = "best"


class Computer(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    name: str
    kind: Literal["robot", "server"]
    capacity: float


class Link(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    between: tuple[str, str]
    bandwidth: float


class Node(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    name: str
    settings: list[Setting]
    weight: float = 1.0
    residence: list[str] | None = None
    coresidence: str | None = None
    continuum: Continuum | None = None
    #: which running process or topic this node is, for characterisation (free text)
    process: str | None = None
    #: ``apply``: this node is an arpz robot's sensor topic, "robot/topic"; the chosen setting's
    #: ``frequency_hz`` is the rate the robot is told to sample it at
    topic: str | None = None
    #: ``apply``: this node is a computation arpz can run on a robot or on the CEDDP (the
    #: hallway mission's "obstacle_check"); its computer decides where
    computation: str | None = None


class Message(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    source: str = msgspec.field(name="from")
    to: str
    #: None: the bandwidth of the source node's chosen setting (Setting.bandwidth)
    bandwidth: float | None = None


class Model(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    computers: list[Computer]
    nodes: list[Node]
    links: list[Link] = msgspec.field(default_factory=list)
    messages: list[Message] = msgspec.field(default_factory=list)
    name: str | None = None
    description: str | None = None


def load_model(path: str | Path) -> Model:
    """Read, decode and validate a model file; raise ModelError naming the file on any problem."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ModelError(f"{path}: cannot read the model file: {exc.strerror or exc}") from exc
    try:
        if path.suffix.lower() == ".toml":
            model = msgspec.convert(tomllib.loads(raw.decode("utf-8")), Model)
        else:
            model = msgspec.json.decode(raw, type=Model)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise ModelError(f"{path}: {exc}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ModelError(f"{path}: not valid TOML: {exc}") from exc
    problems = validate(model)
    if problems:
        raise ModelError(f"{path}: invalid model:\n  - " + "\n  - ".join(problems))
    return model


def decode_model(data: bytes | str, *, fmt: Literal["json", "toml"] = "json") -> Model:
    """Decode and validate a model from text (what load_model does, without a file)."""
    try:
        if fmt == "toml":
            text = data.decode("utf-8") if isinstance(data, bytes) else data
            model = msgspec.convert(tomllib.loads(text), Model)
        else:
            model = msgspec.json.decode(data, type=Model)
    except (msgspec.ValidationError, msgspec.DecodeError, tomllib.TOMLDecodeError) as exc:
        raise ModelError(str(exc)) from exc
    problems = validate(model)
    if problems:
        raise ModelError("invalid model:\n  - " + "\n  - ".join(problems))
    return model


def dump_json(model: Model) -> bytes:
    return msgspec.json.format(msgspec.json.encode(model), indent=2) + b"\n"


def _finite_nonneg(value: float, where: str, problems: list[str]) -> None:
    if not math.isfinite(value):
        problems.append(f"{where} must be a finite number, not {value}")
    elif value < 0:
        problems.append(f"{where} must not be negative, not {value}")


def _duplicates(names: Iterable[str]) -> list[str]:
    seen: set[str] = set()
    dup: list[str] = []
    for name in names:
        if name in seen and name not in dup:
            dup.append(name)
        seen.add(name)
    return dup


def validate(model: Model) -> list[str]:
    """Every problem of a decoded model, as messages that say where and how to fix it."""
    problems: list[str] = []
    computers = {c.name for c in model.computers}
    nodes = {n.name for n in model.nodes}
    if not model.computers:
        problems.append("computers: the model needs at least one computer")
    if not model.nodes:
        problems.append("nodes: the model needs at least one node")
    for name in _duplicates(c.name for c in model.computers):
        problems.append(f"computers: the name {name!r} is used twice; computer names are unique")
    for name in _duplicates(n.name for n in model.nodes):
        problems.append(f"nodes: the name {name!r} is used twice; node names are unique")
    for i, comp in enumerate(model.computers):
        if not comp.name:
            problems.append(f"computers[{i}]: the name is empty")
        _finite_nonneg(comp.capacity, f"computers[{i}] ({comp.name}).capacity", problems)

    pairs: set[frozenset[str]] = set()
    for i, link in enumerate(model.links):
        where = f"links[{i}] ({link.between[0]} - {link.between[1]})"
        for end in link.between:
            if end not in computers:
                problems.append(f"{where}: unknown computer {end!r}; declare it under computers")
        if link.between[0] == link.between[1]:
            problems.append(f"{where}: a link joins two different computers")
        pair = frozenset(link.between)
        if len(pair) == 2 and pair in pairs:
            problems.append(f"{where}: a second link between the same computers; merge them")
        pairs.add(pair)
        _finite_nonneg(link.bandwidth, f"{where}.bandwidth", problems)

    groups: dict[str, list[Node]] = {}
    for i, node in enumerate(model.nodes):
        where = f"nodes[{i}] ({node.name})"
        if not node.name:
            problems.append(f"nodes[{i}]: the name is empty")
        _finite_nonneg(node.weight, f"{where}.weight", problems)
        if not node.settings:
            problems.append(f"{where}.settings is empty: give at least one {{cpu, performance}}")
        for k, setting in enumerate(node.settings):
            _finite_nonneg(setting.cpu, f"{where}.settings[{k}].cpu", problems)
            _finite_nonneg(setting.performance, f"{where}.settings[{k}].performance", problems)
            for field_name in ("frequency_hz", "bandwidth", "parameter"):
                value = getattr(setting, field_name)
                if value is not None:
                    _finite_nonneg(value, f"{where}.settings[{k}].{field_name}", problems)
        if sum(s.fixed for s in node.settings) > 1:
            problems.append(f"{where}: more than one setting is marked fixed; mark at most one")
        if node.residence is not None:
            if not node.residence:
                problems.append(
                    f"{where}.residence is an empty list: use null for anywhere, or name computers"
                )
            for comp_name in node.residence:
                if comp_name not in computers:
                    problems.append(
                        f"{where}.residence: unknown computer {comp_name!r}; "
                        f"known: {', '.join(sorted(computers))}"
                    )
        if node.continuum is not None and node.settings:
            if node.continuum.step <= 0:
                problems.append(f"{where}.continuum.step must be a positive integer")
            else:
                try:
                    expand(
                        [s.cpu for s in node.settings],
                        [s.performance for s in node.settings],
                        node.continuum.fit,
                        node.continuum.step,
                    )
                except FitError as exc:
                    problems.append(f"{where}.continuum: {exc}")
                problems.extend(_continuum_extras(node, where))
        if node.coresidence is not None:
            groups.setdefault(node.coresidence, []).append(node)

    for group, members in groups.items():
        allowed = set(computers)
        for member in members:
            if member.residence is not None:
                allowed &= set(member.residence)
        if not allowed:
            detail = "; ".join(
                f"{m.name}: {', '.join(m.residence) if m.residence else 'anywhere'}"
                for m in members
            )
            problems.append(
                f"coresidence group {group!r}: its nodes must share a computer but their "
                f"residences have none in common ({detail})"
            )

    for i, msg in enumerate(model.messages):
        where = f"messages[{i}] ({msg.source} -> {msg.to})"
        for end in (msg.source, msg.to):
            if end not in nodes:
                problems.append(f"{where}: unknown node {end!r}; declare it under nodes")
        if msg.source == msg.to:
            problems.append(f"{where}: a node does not send messages to itself")
        if msg.bandwidth is not None:
            _finite_nonneg(msg.bandwidth, f"{where}.bandwidth", problems)
        else:
            source = next((n for n in model.nodes if n.name == msg.source), None)
            if source is not None and any(s.bandwidth is None for s in source.settings):
                problems.append(
                    f"{where}: no bandwidth, and not every setting of {msg.source} gives one; "
                    "give the message a bandwidth or each setting of its source a bandwidth"
                )
    return problems


def _continuum_extras(node: Node, where: str) -> list[str]:
    """A continuum's parameter, frequency and bandwidth must be given on all settings or none,
    and the parameter curves must be invertible."""
    problems: list[str] = []
    assert node.continuum is not None
    for field_name in ("parameter", "frequency_hz", "bandwidth"):
        given = [getattr(s, field_name) is not None for s in node.settings]
        if any(given) and not all(given):
            problems.append(
                f"{where}: {field_name} is given on some settings only; a continuum interpolates "
                "it, so give it on every setting or on none"
            )
    if all(s.parameter is not None for s in node.settings) and node.settings:
        try:
            parameter_curves(
                [s.parameter or 0.0 for s in node.settings],
                [s.cpu for s in node.settings],
                [s.performance for s in node.settings],
                node.continuum.parameter_fit,
            )
        except FitError as exc:
            problems.append(f"{where}.continuum.parameter_fit: {exc}")
    return problems


def node_options(node: Node) -> list[tuple[float, float]]:
    """The (CPU, performance) settings Problem 1 may choose from: listed, or the continuum."""
    if node.continuum is None:
        return [(s.cpu, s.performance) for s in node.settings]
    _, points = expand(
        [s.cpu for s in node.settings],
        [s.performance for s in node.settings],
        node.continuum.fit,
        node.continuum.step,
    )
    return points


@dataclass(frozen=True)
class SettingDetail:
    """One setting a solver may choose, with what a solution reports and what bandwidth its
    messages need: listed as characterised, or interpolated along a continuum."""

    cpu: float
    performance: float
    parameter: float | None = None
    frequency_hz: float | None = None
    bandwidth: float | None = None


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 4)


def node_details(node: Node) -> list[SettingDetail]:
    """``node_options`` with each setting's parameter, frequency and bandwidth.

    Along a continuum, the parameter is the one whose fitted CPU (Fig. 3's CPU-vs-parameter
    regression) is the setting's CPU; frequency and bandwidth are linear in the parameter
    (Table I: Tracker's and Navigation's frequency and bandwidth grow in step with their Hz),
    or in CPU when no parameter is given.
    """
    if node.continuum is None:
        return [
            SettingDetail(s.cpu, s.performance, s.parameter, s.frequency_hz, s.bandwidth)
            for s in node.settings
        ]
    settings = node.settings
    points = node_options(node)
    params: list[float | None] = [None] * len(points)
    axis = [s.cpu for s in settings]
    at = [u for u, _ in points]
    if all(s.parameter is not None for s in settings):
        curves = parameter_curves(
            [s.parameter or 0.0 for s in settings],
            [s.cpu for s in settings],
            [s.performance for s in settings],
            node.continuum.parameter_fit,
        )
        params = [curves.parameter_at(u) for u in at]
        axis = [s.parameter or 0.0 for s in settings]
        at = [p or 0.0 for p in params]

    def along(field_name: str) -> list[float | None]:
        values = [getattr(s, field_name) for s in settings]
        if any(v is None for v in values):
            return [None] * len(points)
        if len(set(axis)) < 2:
            return [values[0]] * len(points)
        line = fit(axis, values, "linear", scale=1.0)
        return [max(line(x), 0.0) for x in at]

    freq, bandwidth = along("frequency_hz"), along("bandwidth")
    return [
        SettingDetail(u, p, _rounded(params[i]), _rounded(freq[i]), _rounded(bandwidth[i]))
        for i, (u, p) in enumerate(points)
    ]


def message_bandwidth(message: Message, source: SettingDetail | None) -> float:
    """A message's bandwidth: its own, else its source's at the chosen setting (0 if unknown)."""
    if message.bandwidth is not None:
        return message.bandwidth
    if source is None or source.bandwidth is None:
        return 0.0
    return source.bandwidth


def fixed_setting(node: Node) -> Setting:
    """The setting Problem 2 uses: the one marked fixed, else the highest-performance one.

    The paper's Problem 2 evaluation "set[s] the maximum value for each node parameter, which
    translates into the maximum performance (and CPU requirement)"; a single setting is trivially
    that one.
    """
    for setting in node.settings:
        if setting.fixed:
            return setting
    return max(node.settings, key=lambda s: (s.performance, s.cpu))


def _without_none(value: object) -> object:
    """TOML has no null: an unset field is left out, at any depth."""
    if isinstance(value, dict):
        return {k: _without_none(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [_without_none(v) for v in value]
    return value


def dump_toml(model: Model) -> str:
    """The model as TOML, in the order people read it: name and description, then computers,
    links, nodes and messages (an empty section is left out)."""
    raw = msgspec.to_builtins(model)
    ordered = {
        key: _without_none(raw[key])
        for key in ("name", "description", "computers", "links", "nodes", "messages")
        if raw.get(key) not in (None, [])
    }
    return tomli_w.dumps(ordered)
