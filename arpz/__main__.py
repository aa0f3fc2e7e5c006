"""``python -m arpz COMMAND``: the entry point for everything that is not a robot or a server.

Commands: ``demo`` (a local fleet on loopback). Robots run ``python -m arpz.robot``, the server
``python -m arpz.ceddp``.
"""

from __future__ import annotations

import sys

COMMANDS = {"demo": "run a CEDDP and N robots on loopback and print the summary"}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        print("usage: python -m arpz COMMAND [options]\n\ncommands:", file=sys.stderr)
        for name, text in COMMANDS.items():
            print(f"  {name:10} {text}", file=sys.stderr)
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    if argv[0] == "demo":
        from arpz.demo import main as demo_main

        return demo_main(argv[1:])
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
