"""``python -m arpz COMMAND``: the one entry point that lists and runs every arpz command.

Each command is also a module of its own (``python -m arpz.robot``, ``python -m arpz.ceddp``,
...), the form systemd units and scripts use; both forms take the same options. A command's
module is imported only when it runs, so that a robot install (no server extra) can still list
the commands and run its own.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from dataclasses import dataclass

from arpz.core.version import version_line


@dataclass(frozen=True)
class Command:
    module: str
    summary: str


COMMANDS: dict[str, Command] = {
    "demo": Command(
        "arpz.tools.demo", "a CEDDP and N robots on loopback, with the reconciled summary"
    ),
    "robot": Command("arpz.robot.__main__", "run a robot agent (sensing, local cache, actuation)"),
    "ceddp": Command("arpz.ceddp.__main__", "run the CEDDP server: router, planner, optimisers"),
    "topic": Command("arpz.tools.topic", "list, info, echo, hz, bw, delay of a fleet's topics"),
    "record": Command("arpz.tools.record", "record a running fleet into MCAP"),
    "play": Command("arpz.tools.play", "play an MCAP recording back into a fleet"),
    "service": Command("arpz.tools.service", "list and call the robots' services (request/reply)"),
    "doctor": Command("arpz.tools.doctor", "check a running fleet and say what is wrong"),
    "bridge": Command("arpz.bridge.__main__", "the ROS 2 bridge (rmw_zenoh), standalone"),
    "perf": Command("arpz.perf.__main__", "performance tests: channel, ingest, fleet scaling"),
    "netem": Command("arpz.netem.__main__", "the lossy-link emulator (a UDP/TCP proxy)"),
    "lab": Command("arpz.lab.__main__", "the kernel network lab: namespaces, loss, roaming (root)"),
    "experiment": Command("arpz.experiment.__main__", "experiment grids, results and figures"),
    "configure": Command("arpz.configure.__main__", "seed 002's configuration optimiser"),
}


def usage() -> str:
    lines = ["usage: python -m arpz COMMAND [options]   (or: arpz COMMAND [options])", ""]
    lines.append("commands:")
    lines += [f"  {name:11} {command.summary}" for name, command in COMMANDS.items()]
    lines += [
        "",
        "options:",
        "  -h, --help     this list; `python -m arpz COMMAND --help` for a command's options",
        "  --version      arpz's, Zenoh's and Python's versions",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    if argv[0] == "--version":
        print(version_line())
        return 0
    command = COMMANDS.get(argv[0])
    if command is None:
        close = [name for name in COMMANDS if name.startswith(argv[0][:2])]
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        print(f"arpz: error: unknown command {argv[0]!r}{hint}\n\n{usage()}", file=sys.stderr)
        return 2
    run: Callable[[list[str]], int] = importlib.import_module(command.module).main
    return run(argv[1:])


if __name__ == "__main__":
    raise SystemExit(main())
