"""The paper's case study (Table I) scaled to any number of robots, cameras and computers.

Choices the paper leaves open follow the authors' code (see ../shared/notes/allocation.md and
docs/configure.md): robots have capacity 100 and servers 400; computers are numbered robots
first, then servers; every robot has a wireless link to every higher-numbered computer, all of
them sharing one 54 Mb/s channel (54000 // number of wireless links each); servers are wired at
100000. Weights are Table I's, divided by their sum so that they sum to 1 (eq. 6).

Figure 2 (the node graph) is not in the text; the eight internal messages per robot are the
data flow the paper describes: the base (Youbot_core) feeds laser and odometry to AMCL and
Navigation, AMCL's pose goes to Environment and Navigation, Environment feeds Model, Model the
Planner, the Planner's costmap the Navigation, whose velocity goes back to the base.
"""

from __future__ import annotations

from collections.abc import Sequence

from arpz.configure.model import Computer, Continuum, Link, Message, Model, Node, Setting

#: (U, P, frequency Hz, parameter) of Table I
TRACKER = [(80, 40, 10, 10), (120, 70, 15, 15), (160, 90, 20, 20), (200, 100, 25, 25)]
#: Table I prints 40 and 60; the authors' code (and its fitted curve) uses 39 and 59
MODEL = [(17, 20, 10, 4), (39, 70, 10, 3500), (59, 100, 10, 10000)]
AMCL = [(19, 20, 2.5, 200), (41, 50, 2.5, 500), (66, 100, 2.5, 3000)]
NAVIGATION = [(25, 10, 2, 2), (39, 65, 10, 10), (50, 100, 20, 20)]
#: the four fitted curves of the paper (Figure 4) as reported by the authors' code
FITS = {"tracker": "log", "model": "log", "amcl": "poly2", "navigation": "log"}
WEIGHTS = {
    "experiment": 0.05,
    "tracker": 0.2,
    "environment": 0.05,
    "model": 0.2,
    "planner": 0.05,
    "amcl": 0.2,
    "navigation": 0.2,
    "youbot_core": 0.05,
}
ROBOT_CAPACITY = 100.0
SERVER_CAPACITY = 400.0
WIRELESS_TOTAL = 54000
WIRED = 100000.0
#: (computers, robots, cameras) of instances 1-10; 1-6 are the paper's Table II
INSTANCES = [
    (2, 1, 1),
    (2, 1, 2),
    (2, 1, 3),
    (3, 2, 1),
    (3, 2, 2),
    (3, 2, 3),
    (4, 3, 1),
    (4, 3, 2),
    (4, 3, 3),
    (4, 3, 4),
]


def _settings(rows: Sequence[tuple[float, float, float, float]]) -> list[Setting]:
    top = max(range(len(rows)), key=lambda i: rows[i][1])
    return [
        Setting(cpu=u, performance=p, frequency_hz=f, parameter=x, fixed=(i == top))
        for i, (u, p, f, x) in enumerate(rows)
    ]


def _one(cpu: float, freq: float) -> list[Setting]:
    return [Setting(cpu=cpu, performance=100, frequency_hz=freq)]


def case_study(robots: int, cameras: int, computers: int, *, step: int = 1) -> Model:
    """The case study with ``robots`` robots, ``cameras`` cameras and ``computers`` computers
    (robots + servers, at least one server)."""
    if robots < 1 or cameras < 0 or computers <= robots:
        raise ValueError(
            "need robots >= 1, cameras >= 0 and computers > robots (at least one server)"
        )
    servers = computers - robots
    robot_names = [f"robot{i}" for i in range(1, robots + 1)]
    server_names = [f"server{i}" for i in range(1, servers + 1)]
    comps = [Computer(name=r, kind="robot", capacity=ROBOT_CAPACITY) for r in robot_names]
    comps += [Computer(name=s, kind="server", capacity=SERVER_CAPACITY) for s in server_names]
    order = robot_names + server_names
    wireless = [(order[i], order[j]) for i in range(robots) for j in range(i + 1, len(order))]
    share = float(WIRELESS_TOTAL // max(len(wireless), 1))
    links = [Link(between=pair, bandwidth=share) for pair in wireless]
    links += [
        Link(between=(server_names[i], server_names[j]), bandwidth=WIRED)
        for i in range(servers)
        for j in range(i + 1, servers)
    ]

    n_nodes = 1 + cameras + 6 * robots
    total_w = (
        WEIGHTS["experiment"]
        + cameras * WEIGHTS["tracker"]
        + robots
        * sum(
            WEIGHTS[k]
            for k in ("environment", "model", "planner", "amcl", "navigation", "youbot_core")
        )
    )

    def w(kind: str) -> float:
        return WEIGHTS[kind] / total_w

    def cont(kind: str) -> Continuum:
        return Continuum(fit=FITS[kind], step=step)  # type: ignore[arg-type]

    nodes = [
        Node(
            name="experiment", weight=w("experiment"), residence=server_names, settings=_one(1, 10)
        )
    ]
    for k in range(1, cameras + 1):
        nodes.append(
            Node(
                name=f"tracker{k}",
                weight=w("tracker"),
                residence=server_names,
                settings=_settings(TRACKER),
                continuum=cont("tracker"),
            )
        )
    messages: list[Message] = []
    for i in range(1, robots + 1):
        nodes += [
            Node(name=f"environment{i}", weight=w("environment"), settings=_one(1, 10)),
            Node(
                name=f"model{i}",
                weight=w("model"),
                settings=_settings(MODEL),
                continuum=cont("model"),
            ),
            Node(
                name=f"planner{i}",
                weight=w("planner"),
                coresidence=f"navigation{i}",
                settings=_one(1, 10),
            ),
            Node(
                name=f"amcl{i}", weight=w("amcl"), settings=_settings(AMCL), continuum=cont("amcl")
            ),
            Node(
                name=f"navigation{i}",
                weight=w("navigation"),
                coresidence=f"navigation{i}",
                settings=_settings(NAVIGATION),
                continuum=cont("navigation"),
            ),
            Node(
                name=f"youbot_core{i}",
                weight=w("youbot_core"),
                residence=[f"robot{i}"],
                settings=_one(16, 10),
            ),
        ]
        flows = [
            ("youbot_core", "amcl"),
            ("youbot_core", "navigation"),
            ("amcl", "environment"),
            ("amcl", "navigation"),
            ("environment", "model"),
            ("model", "planner"),
            ("planner", "navigation"),
            ("navigation", "youbot_core"),
        ]
        messages += [Message(source=f"{a}{i}", to=f"{b}{i}", bandwidth=1) for a, b in flows]
    for k in range(1, cameras + 1):
        messages.append(Message(source=f"tracker{k}", to="environment1", bandwidth=3))
    for i in range(1, robots + 1):
        for j in range(i + 1, robots + 1):
            messages.append(Message(source=f"environment{i}", to=f"environment{j}", bandwidth=1))
    assert len(nodes) == n_nodes
    return Model(
        name=f"case study: {robots} robots, {cameras} cameras, {computers} computers",
        description="Cano et al. 2016, Table I scaled as Table II (generated by arpz.configure)",
        computers=comps,
        links=links,
        nodes=nodes,
        messages=messages,
    )


def paper_instance(number: int) -> Model:
    """Instance 1-10 (1-6 are the paper's Table II)."""
    computers, robots, cameras = INSTANCES[number - 1]
    return case_study(robots, cameras, computers)
