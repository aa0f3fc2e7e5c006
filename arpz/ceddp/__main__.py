"""``python -m arpz.ceddp --config ceddp.toml``: run the CEDDP server (the fleet's Zenoh router).

``python -m arpz.ceddp optimise ...``: the QoS balancing optimiser of seed 001 (see
docs/qos-optimiser.md). Exit codes: 0 clean stop, 1 runtime failure, 2 bad configuration.
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import socket
import sys
from pathlib import Path
from typing import Any, NoReturn

import msgspec

from arpz.ceddp.planner import Planner
from arpz.core.config import CeddpConfig, ConfigError, PluginConfig, from_dict, load_toml
from arpz.core.endpoints import DEFAULT_LISTEN, plain_tcp_beside_tls, resolve
from arpz.core.transport import SessionSettings, TransportError
from arpz.runtime.plugins import load_class
from arpz.runtime.startup import add_version_option, configure_logging, stop_on_signals
from arpz.transport.zenoh import ZenohTransport, config_endpoints, load_zenoh_config, uses_tls

log = logging.getLogger("arpz.ceddp")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m arpz.ceddp", description=__doc__)
    add_version_option(parser)
    parser.add_argument("--config", type=Path, help="CEDDP TOML file")
    parser.add_argument("--fleet", help="overrides fleet")
    parser.add_argument("--listen", help="overrides listen (comma-separated endpoints)")
    parser.add_argument("--rrd", help="overrides rrd (the Rerun recording to write)")
    parser.add_argument("--grpc-port", type=int, help="serve a live Rerun gRPC sink on this port")
    parser.add_argument("--summary-json", help="write a JSON summary here at shutdown")
    parser.add_argument("--duration", type=float, dest="duration_s", help="seconds, 0 = forever")
    parser.add_argument("--no-cache-control", action="store_true")
    parser.add_argument(
        "--planner",
        action="append",
        default=[],
        metavar="MODULE:CLASS",
        help="run this planner class too (repeatable; beside the TOML's [[planners]])",
    )
    parser.add_argument("--log-level", default="INFO")
    return parser.parse_args(argv)


def load(args: argparse.Namespace) -> CeddpConfig:
    overrides: dict[str, Any] = {
        "fleet": args.fleet,
        "rrd": args.rrd,
        "grpc_port": args.grpc_port,
        "summary_json": args.summary_json,
        "duration_s": args.duration_s,
        "listen": args.listen.split(",") if args.listen else None,
        "cache_control": False if args.no_cache_control else None,
    }
    if args.config is not None:
        config = load_toml(args.config, CeddpConfig, overrides)
    else:
        config = from_dict({}, CeddpConfig, overrides, source="command line")
    if args.config is not None and config.msg_paths:  # relative to the config's folder
        folder = args.config.parent
        config = msgspec.structs.replace(
            config, msg_paths=[str(folder / path) for path in config.msg_paths]
        )
    given = [from_dict({"class": spec}, PluginConfig, source="--planner") for spec in args.planner]
    planners = [*config.planners, *given]
    for i, entry in enumerate(planners):  # a wrong name stops the CEDDP before it starts
        load_class(entry.cls, Planner, setting=f"planners[{i}] ({entry.cls})")
    return msgspec.structs.replace(config, planners=planners)


def resolve_listen(config: CeddpConfig, source: str) -> CeddpConfig:
    """The config with its listen endpoints in force (the TOML's, else zenoh_config's, else the
    default), refusing plain ``tcp/`` next to a TLS setup unless ``allow_plain_tcp``."""
    zconf = load_zenoh_config(config.zenoh_config, source=source) if config.zenoh_config else None
    from_file = config_endpoints(zconf, "listen") if zconf is not None else []
    listen = resolve(config.listen, from_file, DEFAULT_LISTEN)
    plain = plain_tcp_beside_tls(listen) if zconf is not None and uses_tls(zconf) else []
    if plain and not config.allow_plain_tcp:
        i = plain[0]
        raise ConfigError(
            f"{source}: listen[{i}] {listen[i]!r} is plain TCP while zenoh_config "
            f"{config.zenoh_config} sets up TLS: listen on tls/ only"
            + ("" if config.listen else " (the TOML lists no listen endpoint, nor does the JSON5)")
            + ", or set allow_plain_tcp = true to accept unencrypted robots"
        )
    return msgspec.structs.replace(config, listen=listen)


def with_ports_chosen(listen: list[str]) -> list[str]:
    """Port 0 ("any free port") replaced by a port that is free now, so that the CEDDP can print
    the endpoint robots must connect to: Zenoh does not tell which port it picked without its
    admin space, which the CEDDP keeps closed. The port is free when chosen; another process
    taking it in the next milliseconds makes the start fail loudly, never silently."""
    chosen = []
    for endpoint in listen:
        proto, _, rest = endpoint.partition("/")
        address, sep, params = rest.partition("#")
        host, colon, port = address.rpartition(":")
        if colon and port == "0" and proto in ("tcp", "tls", "ws", "udp", "quic"):
            kind = socket.SOCK_DGRAM if proto in ("udp", "quic") else socket.SOCK_STREAM
            family = socket.AF_INET6 if host.startswith("[") else socket.AF_INET
            with socket.socket(family, kind) as probe:
                probe.bind((host.strip("[]"), 0))
                port = str(probe.getsockname()[1])
            endpoint = f"{proto}/{host}:{port}{sep}{params}"
        chosen.append(endpoint)
    return chosen


def connect_hint(listen: list[str]) -> str:
    """What a robot passes to ``--connect``: a wildcard address becomes "THIS_HOST"."""
    hints = [
        endpoint.replace("0.0.0.0", "THIS_HOST").replace("[::]", "THIS_HOST") for endpoint in listen
    ]
    return ",".join(hints)


def freeze_start_up() -> None:
    """Keep what start-up allocated (the modules of numpy, rerun, zenoh and, once imported,
    cvxpy, and the server's own structures: 67 000-121 000 objects) out of the garbage
    collector's full passes, which walk every tracked object with the GIL held and stop the
    sensor path meanwhile. At 50 robots x 8 topics x 100 Hz a full pass during the load took
    40-55 ms of CPU (50-105 ms of wall time) without, 10-12 ms (about 22 ms) with (issue 17,
    benchmarks/investigations/README.md, stop 36; ``python benchmarks/investigations/gc_freeze.py``
    prints the pass over the
    CEDDP's start-up with a stand-in for its run-time objects). Start-up objects live as long as
    the process: freezing them frees nothing the collector would have freed."""
    gc.collect()
    gc.freeze()


def serve(argv: list[str] | None) -> int:
    args = parse_args(argv)
    configure_logging(args.log_level)
    try:
        config = load(args)
        config = resolve_listen(config, str(args.config or "command line"))
        config = msgspec.structs.replace(config, listen=with_ports_chosen(config.listen))
    except ConfigError as exc:
        print(f"arpz ceddp: error: bad configuration: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"arpz ceddp: error: cannot choose a free port for listen: {exc}", file=sys.stderr)
        return 2
    try:
        from arpz.ceddp.dashboard import Dashboard
    except ImportError as exc:
        print(
            f"arpz ceddp: error: the server needs its extra dependencies ({exc.name} is missing): "
            "pip install 'arpz[server]'",
            file=sys.stderr,
        )
        return 1
    from arpz.ceddp.server import CeddpServer

    stop = stop_on_signals()
    try:
        transport = ZenohTransport.open(
            SessionSettings(
                mode="router",
                listen=config.listen,
                connect=config.connect,
                config_file=config.zenoh_config,
            )
        )
    except TransportError as exc:
        print(f"arpz ceddp: error: {exc}", file=sys.stderr)
        return 1
    dashboard = None
    try:
        dashboard = Dashboard(config.rrd, grpc_port=config.grpc_port)
        try:
            server = CeddpServer(config, transport, dashboard=dashboard)
        except ConfigError as exc:  # a configured planner that cannot be made
            print(f"arpz ceddp: error: bad configuration: {exc}", file=sys.stderr)
            return 2
        try:
            server.start()
        except ConfigError as exc:  # a live view's port in use (docs/tools.md "Live views")
            print(f"arpz ceddp: error: bad configuration: {exc}", file=sys.stderr)
            return 2
        freeze_start_up()
        print(
            f"arpz ceddp: ready on {','.join(config.listen)} (fleet {config.fleet!r}, "
            f"rrd {config.rrd}); robots: --connect {connect_hint(config.listen)} "
            f"--fleet {config.fleet}",
            flush=True,
        )
        server.run(stop)
        server.shutdown()
    finally:
        transport.close()
        if dashboard is not None:
            dashboard.close()
    log.info("CEDDP stopped")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("optimise", "optimize"):
        try:
            from arpz.ceddp.optimise_cli import main as optimise_main
        except ImportError as exc:
            print(f"arpz ceddp optimise: error: unavailable: {exc}", file=sys.stderr)
            return 1
        return optimise_main(argv[1:])
    return serve(argv)


def exit_without_teardown(code: int) -> NoReturn:
    """End the process once ``main`` has closed everything, skipping the interpreter's teardown.

    By then the summary is written, the recording flushed and closed, and the Zenoh session
    closed. At Rmax 1000 with KEEP_LAST(1) (the hallway mission in the lab, 24 000 beams a
    second) the teardown that followed aborted the process with ``FATAL: exception not
    rethrown`` three times in three, after ``CEDDP stopped``: a native thread being ended
    while the interpreter shut down (faulthandler showed no Python frame). The exit code then
    said a successful CEDDP had crashed."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    exit_without_teardown(main())
