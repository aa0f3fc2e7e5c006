"""``python -m arpz.robot --config robot.toml [flags]``: run one robot agent.

Exit codes: 0 clean stop, 1 runtime failure (e.g. the server cannot be reached), 2 bad
configuration (the message names the file, the field and the problem), or a robot_id another
running process of the fleet already uses.
"""

from __future__ import annotations

import argparse
import functools
import logging
import sys
from pathlib import Path
from typing import Any

import msgspec

from arpz.core.config import ConfigError, RobotConfig, from_dict, load_toml
from arpz.core.endpoints import DEFAULT_CONNECT, resolve
from arpz.core.transport import (
    CLIENT_LINK_DEFAULTS,
    SessionSettings,
    TransportError,
    client_link_defaults,
)
from arpz.robot.actuation import CommandTypeError, check_command_contract, make_actuator
from arpz.robot.agent import DuplicateRobotError, RobotAgent, check_robot_id_free
from arpz.robot.link_monitor import LinkWatch
from arpz.robot.sensing import message_types
from arpz.robot.sensors.factory import DriverError
from arpz.robot.sensors.replay import TraceError
from arpz.robot.summary import RobotSummary
from arpz.runtime.startup import add_version_option, configure_logging, stop_on_signals
from arpz.transport.zenoh import (
    ZenohTransport,
    config_endpoints,
    config_value,
    load_zenoh_config,
)

log = logging.getLogger("arpz.robot")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m arpz.robot", description=__doc__)
    add_version_option(parser)
    parser.add_argument("--config", type=Path, help="robot TOML file")
    parser.add_argument("--robot-id", help="overrides robot_id")
    parser.add_argument("--fleet", help="overrides fleet")
    parser.add_argument("--connect", help="overrides connect (comma-separated endpoints)")
    parser.add_argument("--preset", choices=["machine1", "machine2", "machine3"])
    parser.add_argument("--rate", type=float, dest="preset_rate_hz", help="preset sensor rate (Hz)")
    parser.add_argument("--duration", type=float, dest="duration_s", help="seconds, 0 = forever")
    parser.add_argument("--seed", type=int)
    parser.add_argument("--hello", action="store_true", help="be the Hello origin")
    parser.add_argument("--no-local-cache", action="store_true", help="send every reading")
    parser.add_argument(
        "--sim", metavar="WORLD", help="simulate the body in a 2-D world: 'hallway' or a map file"
    )
    parser.add_argument(
        "--summary-json",
        type=Path,
        metavar="PATH",
        help="write this robot's own summary here (its counts, its link's drops), atomically, "
        "at exit and after each drop and reconnection",
    )
    parser.add_argument(
        "--actuator",
        metavar="MODULE:CLASS",
        help="the team's actuator class (overrides the TOML's [actuator]; docs/nodes.md)",
    )
    parser.add_argument("--log-level", default="INFO")
    return parser.parse_args(argv)


def load(args: argparse.Namespace) -> RobotConfig:
    overrides: dict[str, Any] = {
        "robot_id": args.robot_id,
        "fleet": args.fleet,
        "preset": args.preset,
        "preset_rate_hz": args.preset_rate_hz,
        "duration_s": args.duration_s,
        "seed": args.seed,
        "connect": args.connect.split(",") if args.connect else None,
    }
    if args.config is not None:
        config = load_toml(args.config, RobotConfig, overrides)
        source = str(args.config)
    else:
        if not args.robot_id:
            raise ConfigError("command line: give --config FILE or at least --robot-id")
        config = from_dict({}, RobotConfig, overrides, source="command line")
        source = "command line"
    extra: dict[str, Any] = {}
    if args.hello:
        extra["hello"] = {"enabled": True}
    if args.no_local_cache:
        extra["local_cache"] = {"enabled": False}
    if args.sim:
        extra["sim"] = {"world": args.sim}
    if args.actuator:
        extra["actuator"] = {"class": args.actuator}
    if extra:
        import msgspec

        merged = msgspec.to_builtins(config)
        for key, value in extra.items():
            merged[key] = {**(merged.get(key) or {}), **value}
        config = from_dict(merged, RobotConfig, source=source)
    return config


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    configure_logging(args.log_level)
    try:
        config = load(args)
        zconf = None
        if config.zenoh_config:
            zconf = load_zenoh_config(
                config.zenoh_config, source=str(args.config or "command line")
            )
        from_file = config_endpoints(zconf, "connect") if zconf is not None else []
        config = msgspec.structs.replace(
            config, connect=resolve(config.connect, from_file, DEFAULT_CONNECT)
        )
        actuator = make_actuator(config.actuator) if config.actuator is not None else None
        # the typed sensors' types and msg_paths: refused here, before the robot connects
        message_types(config, args.config.parent if args.config is not None else Path.cwd())
    except ConfigError as exc:
        flag = " (given by --connect)" if args.connect and "connect[" in str(exc) else ""
        print(f"arpz robot: error: bad configuration: {exc}{flag}", file=sys.stderr)
        return 2
    if not config.sensors and config.preset is None and config.sim is None:
        log.warning(
            "robot %s has no sensors: it will only act on commands and serve its services (give "
            "[[sensors]] in the TOML, --preset or --sim to make it sense)",
            config.robot_id,
        )
    stop = stop_on_signals()
    # a --duration shorter than the connect timeout bounds the wait too: the user asked for a
    # run of that length, not for one that may sit 30 s trying to reach an absent server
    timeout_s = config.connect_timeout_s
    if config.duration_s > 0:
        timeout_s = min(timeout_s, config.duration_s)
    print(
        f"arpz robot: {config.robot_id} connecting to {','.join(config.connect)} "
        f"(fleet {config.fleet!r}, up to {timeout_s:g} s)",
        flush=True,
    )
    try:
        transport = ZenohTransport.open(
            SessionSettings(
                mode="client",
                connect=config.connect,
                config_file=config.zenoh_config,
                defaults=client_link_defaults(config.connect),
            ),
            timeout_s=timeout_s,
        )
    except TransportError as exc:
        print(f"arpz robot: error: {exc}", file=sys.stderr)
        return 1
    try:
        # before the agent declares anything: a second process with this robot_id is refused
        lease = config_value(zconf, "transport/link/tx/lease") if zconf is not None else None
        if not isinstance(lease, int | float):
            lease = CLIENT_LINK_DEFAULTS["transport/link/tx/lease"]
        assert isinstance(lease, int | float)
        try:
            check_robot_id_free(transport, config, linger_s=lease / 1000 + 1.0)
        except DuplicateRobotError as exc:
            print(f"arpz robot: error: {exc}", file=sys.stderr)
            return 2
        if actuator is not None:  # the CEDDP's planners send what this actuator takes
            try:
                check_command_contract(transport, config, actuator)
            except CommandTypeError as exc:
                print(f"arpz robot: error: bad configuration: {exc}", file=sys.stderr)
                return 2
        base_dir = args.config.parent if args.config is not None else Path.cwd()
        try:
            agent = RobotAgent(config, transport, base_dir=base_dir, actuator=actuator)
        except (DriverError, TraceError, ValueError) as exc:
            print(
                f"arpz robot: error: bad configuration: {args.config or 'command line'}: {exc}",
                file=sys.stderr,
            )
            return 2
        summary = RobotSummary(args.summary_json, agent) if args.summary_json else None
        watch: LinkWatch | None = None
        try:
            if config.link.reopen:
                # from the session's first moment: a roam during start-up is one too
                watch = agent.watch_link(transport)
                if summary is not None:
                    summary.watch = watch
                    watch.on_change = functools.partial(summary.write, complete=False)
                watch.start()
            agent.start()
            print(
                f"arpz robot: {config.robot_id} running ({len(agent.sensors)} sensors)", flush=True
            )
            agent.run(stop)
            agent.shutdown()
        finally:
            if watch is not None:
                watch.stop()
            if summary is not None:
                summary.write(complete=agent.final_stats is not None)
    finally:
        transport.close()
    log.info("robot %s stopped", config.robot_id)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
