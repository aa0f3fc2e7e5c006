"""``python -m arpz service``: ``ros2 service`` for an arpz fleet (docs/tools.md, "Services").

    python -m arpz service list [--json]
    python -m arpz service call /robot1/dock std_srvs/srv/Trigger '{}'
    python -m arpz service call /robot1/lamp std_srvs/srv/SetBool '{data: true}' --timeout 2

The tool joins the fleet's router as a Zenoh client (scouting off), learns the robots' services
from their announcements (``list``) and calls one through ``arpz.ceddp.services.ServiceCaller``
(``call``), the CEDDP's own caller. Exit codes of ``call``: 0 the response came, 1 no response
(the handler failed, the call timed out, the robot is gone or access control refused it), 2 bad
input (a service, type or request that cannot be used). Every exit path closes the session.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import sys
import time
from typing import Any, Final

from arpz.ceddp.services import (
    DEFAULT_TIMEOUT_S,
    FleetServices,
    NoSuchService,
    ServiceCaller,
    ServiceError,
    ServiceTypeError,
)
from arpz.core import keys
from arpz.core.errors import ArpzError
from arpz.core.msgtypes import MessageTypes, MessageValueError, as_dict
from arpz.core.transport import SessionSettings
from arpz.runtime.startup import (
    JSON_TO_STDOUT,
    add_fleet_client_options,
    add_json_option,
    add_version_option,
    connect_endpoints,
    emit_json,
    fail,
    stop_on_signals,
)
from arpz.tools.fleet_graph import CeddpStatsWatch
from arpz.tools.topic_text import yaml_text
from arpz.transport.zenoh import ZenohTransport

TOOL: Final = "service"
#: how long ``call`` waits for the fleet's tokens and the CEDDP's report (access control in
#: force?) before calling: a call that gets no answer is told apart by them
_LOOK_S: Final = 0.7
#: the field ROS 2 gives an empty message, not shown
_PLACEHOLDER: Final = "structure_needs_at_least_one_member"

SERVICE_HELP: Final = (
    "the service: /ROBOT/NAME (/robot1/dock), the same without the leading '/', /ROBOT/srv/NAME, "
    "or its arpz key (arpz/FLEET/robot/ROBOT/srv/NAME)"
)


class BadInput(ArpzError, ValueError):
    """A service name, type or request the tool cannot use (exit 2)."""


def parse_service(fleet: str, given: str) -> tuple[str, str]:
    """(robot, service) of a service named as ``SERVICE_HELP`` says."""
    text = given.strip()
    prefix = f"{keys.fleet_prefix(fleet)}/robot/"
    if text.startswith(f"{keys.ROOT}/"):
        if not text.startswith(prefix):
            raise BadInput(f"{given!r} is not a service key of fleet {fleet!r} ({prefix}...)")
        parts = text[len(prefix) :].split("/")
        if len(parts) == 3 and parts[1] == "srv":
            return _checked(parts[0], parts[2])
        raise BadInput(f"{given!r} is not a service key: {prefix}ROBOT/srv/NAME")
    parts = text.strip("/").split("/")
    if len(parts) == 3 and parts[1] == "srv":
        parts = [parts[0], parts[2]]
    if len(parts) != 2:
        raise BadInput(f"{given!r} does not name a service: write /ROBOT/NAME, e.g. /robot1/dock")
    return _checked(*parts)


def _checked(robot: str, name: str) -> tuple[str, str]:
    try:
        return keys.check_chunk(robot, what="robot id"), keys.check_chunk(name, what="service")
    except keys.KeyExprError as exc:
        raise BadInput(str(exc)) from None


# ----------------------------------------------------------------------------- the request


_TOKEN = re.compile(
    r"""\s*(?:(?P<punct>[{}\[\],:])|(?P<string>"(?:[^"\\]|\\.)*"|'(?:[^'\\]|\\.)*')"""
    r"""|(?P<word>[^\s{}\[\],:'"]+))"""
)


def parse_request(text: str) -> Any:
    """The request as ``ros2 service call`` takes it: JSON, or YAML's flow style (``{data:
    true}``, ``{a: [1, 2], b: {c: x}}``: bare keys, and bare words as strings); an empty
    text is ``{}``. ``BadInput`` saying where it stops making sense."""
    if not text.strip():
        return {}
    try:
        return json.loads(text)
    except ValueError:
        pass
    tokens: list[tuple[str, str]] = []
    at = 0
    while at < len(text):
        if text[at:].strip() == "":
            break
        found = _TOKEN.match(text, at)
        if found is None:
            raise BadInput(f"request: cannot read {text[at:]!r}")
        kind = str(found.lastgroup)
        tokens.append((kind, found.group(kind)))
        at = found.end()
    value, rest = _value(tokens, 0, text)
    if rest != len(tokens):
        raise BadInput(f"request: unexpected {tokens[rest][1]!r} after the value in {text!r}")
    return value


def _value(tokens: list[tuple[str, str]], i: int, text: str) -> tuple[Any, int]:
    if i >= len(tokens):
        raise BadInput(f"request: {text!r} ends too early")
    kind, token = tokens[i]
    if token in "{[" and kind == "punct":
        close = "}" if token == "{" else "]"
        items: list[Any] = []
        pairs: dict[str, Any] = {}
        i += 1
        while i < len(tokens) and tokens[i] != ("punct", close):
            if token == "{":
                key, i = _value(tokens, i, text)
                if tokens[i : i + 1] != [("punct", ":")]:
                    raise BadInput(f"request: a ':' must follow {key!r} in {text!r}")
                pairs[str(key)], i = _value(tokens, i + 1, text)
            else:
                item, i = _value(tokens, i, text)
                items.append(item)
            if tokens[i : i + 1] == [("punct", ",")]:
                i += 1
        if i >= len(tokens):
            raise BadInput(f"request: {text!r} misses a closing {close!r}")
        return (pairs if token == "{" else items), i + 1
    if kind == "punct":
        raise BadInput(f"request: unexpected {token!r} in {text!r}")
    if kind == "string":
        return json.loads(token) if token[0] == '"' else token[1:-1], i + 1
    return _scalar(token), i + 1


def _scalar(word: str) -> Any:
    lowered = word.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    if lowered in ("null", "~"):
        return None
    for kind in (int, float):
        try:
            return kind(word)
        except ValueError:
            pass
    return word


def plain(value: Any) -> Any:
    """A message's dict as JSON takes it: bytes (uint8 arrays) as lists of numbers, and the
    placeholder of an empty message left out."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items() if k != _PLACEHOLDER}
    if isinstance(value, list):
        return [plain(v) for v in value]
    if isinstance(value, bytes | bytearray | memoryview):
        return list(bytes(value))
    return value


# ----------------------------------------------------------------------------- the commands


def _types(paths: list[str]) -> MessageTypes:
    types = MessageTypes()
    if paths:
        types.add_msg_paths(paths)
        types.add_srv_paths(paths)
    return types


def _open(args: argparse.Namespace) -> ZenohTransport:
    """A client session to the fleet's router (``--connect``, ``--zenoh-config``)."""
    settings = SessionSettings(
        mode="client", connect=connect_endpoints(args.connect), config_file=args.zenoh_config
    )
    return ZenohTransport.open(settings, timeout_s=2.0)


def _caller_id() -> str:
    return f"tool:{socket.gethostname()}:{os.getpid()}"


def run_call(args: argparse.Namespace) -> int:
    """Check everything that can be checked before joining the fleet, then call."""
    try:
        robot, name = parse_service(args.fleet, args.service)
        types = _types(args.msg_path)
        request_type, _ = types.service_types(args.type)
        request = parse_request(args.request)
        message = types.check_service_message(request_type, request)
    except (ArpzError, MessageValueError) as exc:
        return fail(TOOL, str(exc))
    shown = plain(as_dict(message))
    if args.json != JSON_TO_STDOUT:
        print(f"requester: making request: {request_type}\n{yaml_text(shown)}\n", flush=True)
    try:
        transport = _open(args)
    except ArpzError as exc:
        return fail(TOOL, str(exc), 1)
    try:
        directory = FleetServices(transport, args.fleet)
        stats = CeddpStatsWatch(transport, args.fleet)
        try:
            stats.wait(_LOOK_S)  # access control in force? (a refusal looks like a gone robot)
            directory.wait(lambda d: d(robot).present is not None, _LOOK_S)
            caller = ServiceCaller(
                transport,
                args.fleet,
                types=types,
                caller=_caller_id(),
                directory=directory,
                access_control=lambda: (
                    latest.access_control if (latest := stats.latest()) is not None else None
                ),
            )
            started = time.monotonic()
            try:
                response = caller.call(robot, name, message, args.timeout, type=args.type)
            except ServiceError as exc:
                return _failed(args, robot, name, exc)
            latency_ms = round((time.monotonic() - started) * 1000, 3)
        finally:
            stats.close()
            directory.close()
    finally:
        transport.close()
    body = plain(as_dict(response))
    emit_json(
        {
            "service": f"/{robot}/{name}",
            "type": args.type,
            "request": shown,
            "response": body,
            "latency_ms": latency_ms,
        },
        args.json,
    )
    if args.json != JSON_TO_STDOUT:
        print(f"response: ({latency_ms:.1f} ms)\n{yaml_text(body)}")
    return 0


def _failed(args: argparse.Namespace, robot: str, name: str, exc: ServiceError) -> int:
    bad_input = isinstance(exc, ServiceTypeError | NoSuchService)
    emit_json(
        {
            "service": f"/{robot}/{name}",
            "type": args.type,
            "error": {"kind": type(exc).__name__, "message": str(exc)},
        },
        args.json,
    )
    return fail(TOOL, f"{type(exc).__name__}: {exc}", 2 if bad_input else 1)


def run_list(args: argparse.Namespace) -> int:
    stop = stop_on_signals()
    try:
        transport = _open(args)
    except ArpzError as exc:
        return fail(TOOL, str(exc), 1)
    try:
        directory = FleetServices(transport, args.fleet)
        try:
            directory.wait(_all_announced, args.discovery_s, stop)
            robots = directory.robots()
        finally:
            directory.close()
    finally:
        transport.close()
    if not robots:
        return fail(
            TOOL,
            f"no robot of fleet {args.fleet!r} seen in {args.discovery_s:g} s at {args.connect}: "
            "check --connect and --fleet",
            1,
        )
    rows = [
        {"name": f"/{robot}/{service}", "robot": robot, "service": service, "type": kind}
        for robot, known in robots.items()
        for service, kind in sorted((known.services or {}).items())
    ]
    silent = sorted(robot for robot, known in robots.items() if known.services is None)
    emit_json({"fleet": args.fleet, "services": rows, "not_announced": silent}, args.json)
    out = sys.stderr if args.json == JSON_TO_STDOUT else sys.stdout
    width = max((len(str(row["name"])) for row in rows), default=0)
    for row in rows:
        print(f"{row['name']:{width}}  [{row['type']}]", file=out)
    if not rows:
        print(f"no services in fleet {args.fleet!r} ({len(robots)} robot(s) seen)", file=out)
    if silent:
        print(f"no announcement yet from: {', '.join(silent)}", file=out)
    return 0


def _all_announced(directory: FleetServices) -> bool:
    """Every robot seen has announced itself (after the tokens' history came)."""
    robots = directory.robots()
    return bool(robots) and all(known.services is not None for known in robots.values())


# ----------------------------------------------------------------------------- the parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="arpz service",
        description="List and call a running fleet's robot services, as `ros2 service` does. "
        "The tool joins the fleet's router as a client.",
        epilog="SERVICE forms: " + SERVICE_HELP + ". See docs/tools.md.",
    )
    add_version_option(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    listing = sub.add_parser(
        "list",
        help="every robot's services with their types",
        description="Every robot's services, from their announcements, with their types.",
    )
    add_fleet_client_options(listing)
    add_json_option(listing, "the services")
    listing.add_argument(
        "--discovery-s",
        type=float,
        default=3.0,
        metavar="S",
        help="wait at most this long for every robot's announcement (default %(default)s)",
    )
    call = sub.add_parser(
        "call",
        help="call SERVICE with a request and print the response",
        description="Call SERVICE of type TYPE with REQUEST and print the response. Exit codes: "
        "0 the response came, 1 none (failed, timed out, gone, refused), 2 bad input.",
    )
    add_fleet_client_options(call)
    add_json_option(call, "the request and response (or the error)")
    call.add_argument("service", metavar="SERVICE", help=SERVICE_HELP)
    call.add_argument("type", metavar="TYPE", help="the service type, e.g. std_srvs/srv/Trigger")
    call.add_argument(
        "request",
        metavar="REQUEST",
        nargs="?",
        default="{}",
        help="the request's fields as JSON or YAML flow style, e.g. '{data: true}' (default '{}')",
    )
    call.add_argument(
        "--timeout",
        type=float,
        default=DEFAULT_TIMEOUT_S,
        metavar="S",
        help="give up after S seconds (default %(default)s)",
    )
    call.add_argument(
        "--msg-path",
        action="append",
        default=[],
        metavar="DIR",
        help="a folder of the fleet's own .msg and .srv files (PACKAGE/msg/, PACKAGE/srv/; "
        "repeatable)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        keys.check_chunk(args.fleet, what="--fleet")
        connect_endpoints(args.connect)
        if args.command == "call" and not args.timeout > 0:
            raise BadInput("--timeout must be > 0 (seconds)")
        if args.command == "list" and not args.discovery_s > 0:
            raise BadInput("--discovery-s must be > 0 (seconds)")
    except ArpzError as exc:
        return fail(TOOL, str(exc))
    try:
        return run_call(args) if args.command == "call" else run_list(args)
    except BrokenPipeError:  # `arpz service list | head`
        return 0


if __name__ == "__main__":
    sys.exit(main())
