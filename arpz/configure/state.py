"""A partial allocation that heuristics edit one unit at a time, keeping loads in step.

Both heuristics (greedy, improved) need the same questions answered fast: does this coresidence
unit fit on that computer, and what would its messages add to each link, given what is already
placed? Messages to nodes not yet placed are not counted (they are counted when the partner is
placed), so a feasible partial allocation stays feasible as it grows.
"""

from __future__ import annotations

from arpz.configure.problem import Problem

EPS = 1e-9


class State:
    def __init__(self, problem: Problem) -> None:
        self.p = problem
        n_nodes = len(problem.nodes)
        self.computer = [-1] * n_nodes
        self.level = [0] * n_nodes
        self.load = [0.0] * len(problem.computers)
        self.capacity = [
            0.0 if problem.growable(c) else problem.capacity[c]
            for c in range(len(problem.computers))
        ]
        self.link_load = [0.0] * len(problem.link_bandwidth)

    def copy(self) -> State:
        other = State.__new__(State)
        other.p = self.p
        other.computer = list(self.computer)
        other.level = list(self.level)
        other.load = list(self.load)
        other.capacity = list(self.capacity)
        other.link_load = list(self.link_load)
        return other

    def cpu(self, n: int) -> float:
        return self.p.options[n][self.level[n]][0]

    def unit_cpu(self, u: int) -> float:
        return sum(self.cpu(n) for n in self.p.units[u])

    def free(self, c: int) -> float:
        return self.capacity[c] - self.load[c]

    def traffic(self, u: int, c: int) -> dict[int, float] | None:
        """Link traffic unit u's messages would add if on computer c (None: an unlinked pair)."""
        members = self.p.units[u]
        delta: dict[int, float] = {}
        for n in members:
            for m, bw in self.p.partners[n]:
                if self.p.unit_of[m] == u:
                    continue
                d = self.computer[m]
                if d < 0 or d == c:
                    continue
                link = self.p.link_between(c, d)
                if link is None:
                    return None
                delta[link] = delta.get(link, 0.0) + bw
        return delta

    def bandwidth_ok(self, delta: dict[int, float]) -> bool:
        bw = self.p.link_bandwidth
        return all(self.link_load[k] + v <= bw[k] + EPS for k, v in delta.items())

    def can_place(self, u: int, c: int, *, grow: bool = False) -> dict[int, float] | None:
        """The traffic delta if unit u (not placed) may go on c, else None."""
        if c not in self.p.unit_allowed[u]:
            return None
        if not grow and self.unit_cpu(u) > self.free(c) + EPS:
            return None
        delta = self.traffic(u, c)
        if delta is None or not self.bandwidth_ok(delta):
            return None
        return delta

    def place(self, u: int, c: int, delta: dict[int, float] | None = None) -> None:
        if delta is None:
            delta = self.traffic(u, c) or {}
        for n in self.p.units[u]:
            self.computer[n] = c
            self.load[c] += self.cpu(n)
        for k, v in delta.items():
            self.link_load[k] += v
        if self.load[c] > self.capacity[c] and self.p.growable(c):
            self.capacity[c] = self.load[c]

    def remove(self, u: int) -> int:
        members = self.p.units[u]
        c = self.computer[members[0]]
        for n in members:
            self.computer[n] = -1
            self.load[c] -= self.cpu(n)
        delta = self.traffic(u, c) or {}
        for k, v in delta.items():
            self.link_load[k] -= v
        return c

    def move(self, u: int, c: int) -> bool:
        """Move a placed unit to c if it fits there with its messages; False leaves it in place."""
        old = self.remove(u)
        delta = self.can_place(u, c)
        if delta is None:
            self.place(u, old)
            return False
        self.place(u, c, delta)
        return True
