"""``python -m arpz.bridge --connect ENDPOINT --fleet NAME [--domain-id N] [--config FILE]``:
the ROS 2 bridge on a machine of its own, a client of the fleet's router (docs/ros2.md).
Robots' services are bridged only by the bridge inside the CEDDP (it calls them through the
CEDDP's service caller).

``--config`` is a TOML with the traffic profiles of the fleet (as a robot's), ``fleet``,
``connect`` and a ``[ros2]`` table (topic names, command mappings); the flags override it.
On exit (SIGINT, SIGTERM or ``--duration``) the bridge's counters are printed as JSON
(``--json FILE`` writes them to a file). Exit codes: 0 clean stop, 1 the router could not be
reached, 2 bad configuration.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

import msgspec

from arpz.bridge.factory import bridge_class
from arpz.core.config import BridgeConfig, ConfigError, from_dict, load_toml
from arpz.core.endpoints import DEFAULT_CONNECT
from arpz.core.msgtypes import MessageTypes
from arpz.core.transport import SessionSettings, TransportError
from arpz.runtime.startup import (
    add_fleet_client_options,
    add_json_option,
    add_version_option,
    configure_logging,
    connect_endpoints,
    emit_json,
    fail,
    stop_on_signals,
    wait_for_stop,
)
from arpz.transport.zenoh import ZenohTransport

log = logging.getLogger("arpz.bridge")
TOOL = "bridge"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m arpz.bridge", description=__doc__)
    add_version_option(parser)
    add_fleet_client_options(parser)
    parser.add_argument("--config", type=Path, help="bridge TOML file ([ros2] table and QoS)")
    parser.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID of the ROS 2 side")
    parser.add_argument("--duration", type=float, default=0.0, help="seconds, 0 = until stopped")
    add_json_option(parser, "the bridge's counters at exit")
    parser.add_argument("--log-level", default="INFO")
    return parser.parse_args(argv)


def load(args: argparse.Namespace) -> BridgeConfig:
    """The config file (if any) with the flags applied over it."""
    source = str(args.config) if args.config is not None else "command line"
    base = load_toml(args.config, BridgeConfig) if args.config is not None else BridgeConfig()
    merged: dict[str, Any] = msgspec.to_builtins(base)
    if args.fleet != "default" or args.config is None:
        merged["fleet"] = args.fleet
    if args.connect != ",".join(DEFAULT_CONNECT) or not base.connect:
        merged["connect"] = list(connect_endpoints(args.connect))
    if args.zenoh_config:
        merged["zenoh_config"] = args.zenoh_config
    if args.domain_id is not None:
        merged["ros2"] = {**merged["ros2"], "domain_id": args.domain_id}
    return from_dict(merged, BridgeConfig, source=source)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    configure_logging(args.log_level)
    try:
        config = load(args)
        types = MessageTypes()
        folder = args.config.parent if getattr(args, "config", None) is not None else Path.cwd()
        types.add_msg_paths([folder / path for path in config.msg_paths])
    except ConfigError as exc:
        return fail(TOOL, f"bad configuration: {exc}")
    stop = stop_on_signals()
    try:
        transport = ZenohTransport.open(
            SessionSettings(mode="client", connect=config.connect, config_file=config.zenoh_config),
            timeout_s=5.0,
        )
    except TransportError as exc:
        return fail(TOOL, str(exc), 1)
    try:
        try:
            bridge = bridge_class(config.ros2)(
                transport, config.fleet, config, config.ros2, types=types
            )
            bridge.start()
        except ConfigError as exc:  # backend "rclpy" without a ROS 2 that imports and starts
            return fail(TOOL, f"bad configuration: {exc}")
        print(
            f"arpz bridge: running: node /{config.ros2.node_name} on ROS 2 domain "
            f"{config.ros2.domain_id} ({config.ros2.backend}), fleet {config.fleet!r} via "
            f"{','.join(config.connect)}",
            flush=True,
        )
        wait_for_stop(stop, args.duration if args.duration > 0 else None)
        bridge.close()
        emit_json(bridge.stats(), args.json or "-")
    finally:
        transport.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
