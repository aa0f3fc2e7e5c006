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
from pathlib import Path
from typing import Literal

import msgspec
import tomli_w

from arpz.configure.regression import FitChoice, FitError, expand
from arpz.errors import ArpzError


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
    #: the parameter value that produces this setting (documentation only, e.g. particles)
    parameter: float | None = None


class Continuum(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    fit: FitChoice = "best"
    step: int = 1


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


class Message(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    source: str = msgspec.field(name="from")
    to: str
    bandwidth: float


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
            if setting.frequency_hz is not None:
                _finite_nonneg(
                    setting.frequency_hz, f"{where}.settings[{k}].frequency_hz", problems
                )
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
        _finite_nonneg(msg.bandwidth, f"{where}.bandwidth", problems)
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
