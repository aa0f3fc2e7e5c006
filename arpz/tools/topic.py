"""``python -m arpz topic``: ``ros2 topic`` for an arpz fleet (docs/tools.md, "Topics").

    python -m arpz topic list  --connect tcp/10.0.0.1:7447 --fleet demo
    python -m arpz topic info  /robot1/lidar
    python -m arpz topic echo  /robot1/lidar [--json [FILE]] [--count N] [--reliable]
    python -m arpz topic hz    /robot1/lidar [--window N] [--duration S]
    python -m arpz topic bw    /robot1/camera
    python -m arpz topic delay /robot1/imu

The tool joins the fleet's router as a Zenoh client (scouting off), learns the fleet's graph from
what the fleet already publishes (``arpz.tools.fleet_graph``) and reads a topic the least
intrusive way (``arpz.tools.topic_stream``: a BEST_EFFORT channel reader unless ``--reliable``,
plain Zenoh where the fleet runs ``reliability = "none"``). Every exit path closes the session.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable
from typing import Final

from arpz.core import keys
from arpz.core.errors import ArpzError
from arpz.core.transport import SessionSettings, Transport
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
from arpz.tools.fleet_graph import (
    Discovery,
    FleetGraph,
    TopicEntry,
    UnknownTopicError,
    discovering,
    matches,
)
from arpz.tools.topic_figures import Bw, Delay, Echo, HostClock, Hz, clock_correction
from arpz.tools.topic_stats import DEFAULT_WINDOW
from arpz.tools.topic_stream import open_stream
from arpz.tools.topic_text import (
    Output,
    info_lines,
    list_lines,
    use_msg_paths,
)
from arpz.transport.zenoh import ZenohTransport

TOOL: Final = "topic"
#: how long discovery watches the fleet at most before answering (less once every robot spoke)
DEFAULT_DISCOVERY_S: Final = 3.0

TOPIC_HELP: Final = (
    "the topic, as a ROS 2 name (/robot1/lidar, /robot1/cmd/velocity, /ceddp/stats), the same "
    "without the leading '/' (robot1/lidar), or an arpz key (arpz/FLEET/robot/robot1/sensor/lidar)"
)


#: arpz payload type -> its decoder (arpz/core/messages.py)
def run_list(args: argparse.Namespace, ctx: Context) -> int:
    graph = ctx.graph
    if not graph.nodes and not graph.topics:
        others = (
            f"; this router carries fleets {', '.join(graph.other_fleets)}"
            if (graph.other_fleets)
            else ""
        )
        return fail(
            TOOL,
            f"nothing of fleet {graph.fleet!r} seen in {args.discovery_s:g} s at {args.connect} "
            f"(no CEDDP, no robot): check --connect and --fleet{others}",
            1,
        )
    emit_json(graph.as_dict(), args.json)
    text_out = sys.stderr if args.json == JSON_TO_STDOUT else sys.stdout
    print("\n".join(list_lines(graph)), file=text_out)
    return 0


def run_info(args: argparse.Namespace, ctx: Context) -> int:
    topic = ctx.graph.topic(args.topic)
    emit_json({**topic.as_dict(), "matches": matches(topic)}, args.json)
    text_out = sys.stderr if args.json == JSON_TO_STDOUT else sys.stdout
    print("\n".join(info_lines(topic)), file=text_out)
    return 0


# ----------------------------------------------------------------------------- the stream loop


class Context:
    """What every subcommand gets: the session, the fleet's graph, discovery (kept open) and
    the stop event (SIGINT/SIGTERM)."""

    def __init__(
        self,
        transport: Transport,
        discovery: Discovery,
        graph: FleetGraph,
        stop: threading.Event,
    ) -> None:
        self.transport = transport
        self.discovery = discovery
        self.graph = graph
        self.stop = stop


Handler = Echo | Hz | Bw | Delay


def stream_loop(
    args: argparse.Namespace, ctx: Context, make: Callable[[TopicEntry, Output], Handler]
) -> int:
    """Open the topic's reader and feed its messages to ``make``'s handler until ``--duration``,
    ``--count`` or a signal; figures every second, the counters at the end."""
    topic = ctx.graph.topic(args.topic)
    if args.reliable and ctx.graph.read_only:
        return fail(
            TOOL,
            "--reliable: the CEDDP reports access control in force, under which a tool holds an "
            "observer's rights at most: a RELIABLE reader's token and ACKNACKs would be refused "
            "and it would read nothing; drop --reliable (docs/security.md, the observer)",
        )
    if args.reliable and any(w.qos is not None and not w.qos.reliable for w in topic.writers):
        return fail(
            TOOL,
            f"{topic.name} has a BEST_EFFORT writer, which a RELIABLE reader cannot match: "
            "drop --reliable",
        )
    out = Output(args.json)
    try:
        with open_stream(ctx.transport, topic, reliable=args.reliable) as stream:
            handler = make(topic, out)
            print(
                f"reading {topic.name} ({topic.key}) with a {stream.description}",
                file=sys.stderr,
                flush=True,
            )
            deadline = time.monotonic() + args.duration if args.duration else float("inf")
            next_report = time.monotonic() + 1.0
            while not ctx.stop.is_set() and not handler.done:
                now = time.monotonic()
                if now >= deadline:
                    break
                message = stream.get(min(next_report, deadline, now + 0.2) - now)
                if message is not None:
                    handler.on_message(message)
                if time.monotonic() >= next_report:
                    handler.report(stream)
                    next_report += 1.0
            # stop reading, then take what was already delivered: the final counters and the
            # messages shown agree exactly
            stream.close()
            while not handler.done and (message := stream.get(0.0)) is not None:
                handler.on_message(message)
            handler.final(stream)
    finally:
        out.close()
    return 0


def run_echo(args: argparse.Namespace, ctx: Context) -> int:
    return stream_loop(args, ctx, lambda topic, out: Echo(topic, out, args.count))


def run_hz(args: argparse.Namespace, ctx: Context) -> int:
    return stream_loop(args, ctx, lambda topic, out: Hz(topic, out, args.window))


def run_bw(args: argparse.Namespace, ctx: Context) -> int:
    return stream_loop(args, ctx, lambda topic, out: Bw(topic, out, args.window))


def run_delay(args: argparse.Namespace, ctx: Context) -> int:
    return stream_loop(
        args,
        ctx,
        lambda topic, out: Delay(
            topic,
            out,
            args.window,
            clock_correction(ctx.discovery, topic, HostClock(ctx.transport, args.fleet)),
        ),
    )


COMMANDS: Final[dict[str, Callable[[argparse.Namespace, Context], int]]] = {
    "list": run_list,
    "info": run_info,
    "echo": run_echo,
    "hz": run_hz,
    "bw": run_bw,
    "delay": run_delay,
}


# ----------------------------------------------------------------------------- the parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="arpz topic",
        description="Inspect a running fleet's topics, as `ros2 topic` does: list, info, echo, "
        "hz, bw, delay. The tool joins the fleet's router as a client.",
        epilog="TOPIC forms: " + TOPIC_HELP + ". See docs/tools.md.",
    )
    add_version_option(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    helps = {
        "list": "every topic with its type, rate, QoS and writers",
        "info": "QoS of each writer and reader of TOPIC, matched or incompatible",
        "echo": "print TOPIC's messages, decoded",
        "hz": "TOPIC's rate, with min/max/std dev of the period over a window",
        "bw": "TOPIC's bandwidth and message sizes over a window",
        "delay": "TOPIC's delay from source stamp to arrival, clock offset corrected when known",
    }
    for name, text in helps.items():
        p = sub.add_parser(name, help=text, description=text[0].upper() + text[1:] + ".")
        add_fleet_client_options(p)
        add_json_option(
            p,
            "the messages or the figures (one object per line, then a final summary)"
            if name not in ("list", "info")
            else "the result",
        )
        p.add_argument(
            "--discovery-s",
            type=float,
            default=DEFAULT_DISCOVERY_S,
            metavar="S",
            help="watch the fleet at most this long to learn its topics (default %(default)s)",
        )
        if name == "list":
            continue
        p.add_argument("topic", metavar="TOPIC", help=TOPIC_HELP)
        if name == "info":
            continue
        p.add_argument(
            "--duration",
            type=float,
            default=0.0,
            metavar="S",
            help="stop after S seconds (default: until Ctrl-C)",
        )
        p.add_argument(
            "--reliable",
            action="store_true",
            help="read as a RELIABLE reader (NACKs make the writers resend what this tool "
            "missed; KEEP_ALL writers then wait for it); default BEST_EFFORT, which asks "
            "nothing of the writers",
        )
        if name == "echo":
            p.add_argument(
                "--msg-path",
                action="append",
                default=[],
                metavar="DIR",
                help="a folder of the fleet's own .msg files (PACKAGE/msg/NAME.msg; repeatable): "
                "their typed topics are shown field by field",
            )
            p.add_argument(
                "--count",
                type=int,
                default=0,
                metavar="N",
                help="stop after N messages (default: no limit)",
            )
        else:
            p.add_argument(
                "--window",
                type=int,
                default=DEFAULT_WINDOW,
                metavar="N",
                help="messages in the statistics window (default %(default)s)",
            )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        endpoints = connect_endpoints(args.connect)
        keys.check_chunk(args.fleet, what="--fleet")
        if getattr(args, "duration", 0.0) < 0 or args.discovery_s <= 0:
            raise ArpzError("--duration must be >= 0 and --discovery-s > 0 (seconds)")
        if getattr(args, "window", DEFAULT_WINDOW) < 2 or getattr(args, "count", 0) < 0:
            raise ArpzError("--window must be >= 2 and --count >= 0")
        if getattr(args, "msg_path", None):
            use_msg_paths(args.msg_path)
    except ArpzError as exc:
        return fail(TOOL, str(exc))
    stop = stop_on_signals()
    settings = SessionSettings(mode="client", connect=endpoints, config_file=args.zenoh_config)
    try:
        transport = ZenohTransport.open(settings, timeout_s=2.0)
    except ArpzError as exc:
        return fail(TOOL, str(exc), 1)
    try:
        with discovering(transport, args.fleet) as discovery:
            graph = discovery.settle(max_s=args.discovery_s, stop=stop)
            return COMMANDS[args.command](args, Context(transport, discovery, graph, stop))
    except UnknownTopicError as exc:
        return fail(TOOL, str(exc), 2)
    except ArpzError as exc:
        return fail(TOOL, str(exc), 1)
    except BrokenPipeError:  # `arpz topic echo ... | head`
        return 0
    finally:
        transport.close()


if __name__ == "__main__":
    sys.exit(main())
