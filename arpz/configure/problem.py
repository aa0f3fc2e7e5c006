"""A model compiled for one of the two problems: indices instead of names, settings expanded.

Solvers work on integers (node i, computer c, setting level k) so that their inner loops do not
hash strings; the feasibility checker deliberately does NOT use this module's derived data (it
reads the model again), so a bug here cannot hide itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from arpz.configure.model import (
    Model,
    SettingDetail,
    fixed_setting,
    message_bandwidth,
    node_details,
)

ProblemKind = Literal[1, 2]


@dataclass(frozen=True)
class Problem:
    """Problem 1 (maximise weighted performance) or 2 (minimise server capacity) of a model."""

    kind: ProblemKind
    model: Model
    computers: tuple[str, ...]
    is_server: tuple[bool, ...]
    #: Problem 1: the model's capacities. Problem 2: robots keep theirs, servers are decided.
    capacity: tuple[float, ...]
    nodes: tuple[str, ...]
    weight: tuple[float, ...]
    #: per node, (cpu, performance) settings sorted by CPU (one setting in Problem 2)
    options: tuple[tuple[tuple[float, float], ...], ...]
    #: per node, ``options`` with each setting's parameter, frequency and bandwidth
    details: tuple[tuple[SettingDetail, ...], ...]
    #: per node, the computers its residence (and its coresidence group's) allows
    allowed: tuple[tuple[int, ...], ...]
    #: coresidence groups and lone nodes: what moves as one piece
    units: tuple[tuple[int, ...], ...]
    unit_of: tuple[int, ...]
    unit_allowed: tuple[tuple[int, ...], ...]
    #: (low computer index, high computer index) -> link index
    link: dict[tuple[int, int], int]
    link_bandwidth: tuple[float, ...]
    link_ends: tuple[tuple[int, int], ...]
    #: (source node, destination node, bandwidth). A message whose bandwidth follows its
    #: source's setting reserves the source's largest: the heuristics upgrade settings without
    #: looking at links and the MILPs leave messages out of the settings' choice, so this keeps
    #: every answer within the links (check.py verifies the exact traffic of the chosen setting)
    messages: tuple[tuple[int, int, float], ...]
    #: per node, (other node, bandwidth) for every message it sends or receives
    partners: tuple[tuple[tuple[int, float], ...], ...]

    @classmethod
    def build(cls, model: Model, kind: ProblemKind) -> Problem:
        comp_index = {c.name: i for i, c in enumerate(model.computers)}
        node_index = {n.name: i for i, n in enumerate(model.nodes)}
        all_comps = tuple(range(len(model.computers)))

        options: list[tuple[tuple[float, float], ...]] = []
        details: list[tuple[SettingDetail, ...]] = []
        allowed_sets: list[set[int]] = []
        for node in model.nodes:
            if kind == 1:
                found = sorted(node_details(node), key=lambda d: (d.cpu, d.performance))
            else:
                fixed = fixed_setting(node)
                found = [
                    SettingDetail(
                        fixed.cpu,
                        fixed.performance,
                        fixed.parameter,
                        fixed.frequency_hz,
                        fixed.bandwidth,
                    )
                ]
            details.append(tuple(found))
            options.append(tuple((d.cpu, d.performance) for d in found))
            if node.residence is None:
                allowed_sets.append(set(all_comps))
            else:
                allowed_sets.append({comp_index[c] for c in node.residence})

        groups: dict[str, list[int]] = {}
        units: list[tuple[int, ...]] = []
        for i, node in enumerate(model.nodes):
            if node.coresidence is None:
                units.append((i,))
            else:
                groups.setdefault(node.coresidence, []).append(i)
        units.extend(tuple(members) for members in groups.values())
        units.sort(key=lambda u: u[0])
        unit_of = [0] * len(model.nodes)
        unit_allowed: list[tuple[int, ...]] = []
        for u, members in enumerate(units):
            common = set(all_comps)
            for n in members:
                unit_of[n] = u
                common &= allowed_sets[n]
            unit_allowed.append(tuple(sorted(common)))
        allowed = tuple(unit_allowed[unit_of[n]] for n in range(len(model.nodes)))

        link: dict[tuple[int, int], int] = {}
        ends: list[tuple[int, int]] = []
        for i, lk in enumerate(model.links):
            a, b = sorted((comp_index[lk.between[0]], comp_index[lk.between[1]]))
            link[(a, b)] = i
            ends.append((a, b))

        messages = tuple(
            (
                node_index[m.source],
                node_index[m.to],
                max(message_bandwidth(m, d) for d in details[node_index[m.source]]),
            )
            for m in model.messages
        )
        partners: list[list[tuple[int, float]]] = [[] for _ in model.nodes]
        for a, b, bw in messages:
            partners[a].append((b, bw))
            partners[b].append((a, bw))

        is_server = tuple(c.kind == "server" for c in model.computers)
        return cls(
            kind=kind,
            model=model,
            computers=tuple(c.name for c in model.computers),
            is_server=is_server,
            capacity=tuple(c.capacity for c in model.computers),
            nodes=tuple(n.name for n in model.nodes),
            weight=tuple(n.weight for n in model.nodes),
            options=tuple(options),
            details=tuple(details),
            allowed=allowed,
            units=tuple(units),
            unit_of=tuple(unit_of),
            unit_allowed=tuple(unit_allowed),
            link=link,
            link_bandwidth=tuple(lk.bandwidth for lk in model.links),
            link_ends=tuple(ends),
            messages=messages,
            partners=tuple(tuple(p) for p in partners),
        )

    def growable(self, c: int) -> bool:
        """Problem 2 decides server capacities; everything else keeps its capacity."""
        return self.kind == 2 and self.is_server[c]

    def link_between(self, c: int, d: int) -> int | None:
        return self.link.get((c, d) if c < d else (d, c))
