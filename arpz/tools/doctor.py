"""``python -m arpz doctor``: check a running fleet and say what is wrong, in words.

    python -m arpz doctor --connect tcp/10.0.0.1:7447 --fleet lab [--timeout 5] [--json [FILE]]

The doctor joins the fleet's router as a Zenoh client (scouting off), listens for a few seconds
to what the fleet publishes anyway (the robots' ``RobotStats``, the CEDDP's ``CeddpStats``, the
presence tokens) and prints one line per check, ``OK``, ``WARN`` or ``FAIL`` and a sentence:

- ``router``: the router answers on the endpoints given (which, and how long it tried);
- ``ceddp``: the CEDDP is present and reporting; ``robots``: who is present and reporting;
- ``versions``: the arpz and Zenoh versions of the CEDDP and of every robot, and whether they
  agree;
- ``tls``: the expiry of every certificate the session's Zenoh config names (warned under 30
  days, failed once expired), and whether the CEDDP says it runs TLS;
- ``access control``: whether the CEDDP's Zenoh config enables ``access_control`` (what the
  CEDDP says about itself);
- ``qos``: INCOMPATIBLE_QOS seen by the CEDDP or by any robot;
- ``delivery``: topics with deadline misses, losses, confirmed gaps or refused writes;
- ``sensors``: sensors that gave no reading for a robot's last report interval (failed),
  driver errors and late reads since a robot started (warned);
- ``robot ids``: a robot id two processes run with (the CEDDP's finding, or two incarnations
  reporting in turn while the doctor listened);
- ``clock ROBOT``: each robot's clock offset to the CEDDP against the bound.

Exit codes: 0 when no check failed (warnings allowed), 1 when one did (the router unreachable
included), 2 for bad input. The rules are pure functions (``diagnose``,
``certificate_checks``), unit-tested without a fleet; ``main`` does the I/O.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import importlib
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import msgspec

from arpz.core import keys
from arpz.core.errors import ArpzError
from arpz.core.messages import (
    CEDDP_STATS_DECODER,
    DECODE_ERRORS,
    STATS_DECODER,
    CeddpStats,
    RobotStats,
)
from arpz.core.transport import SessionSettings, TransportError
from arpz.runtime.startup import (
    add_fleet_client_options,
    add_json_option,
    add_version_option,
    connect_endpoints,
    emit_json,
    fail,
)
from arpz.transport.zenoh import ZenohTransport, config_value, load_zenoh_config

TOOL: Final = "doctor"
OK: Final = "OK"
WARN: Final = "WARN"
FAIL: Final = "FAIL"
#: the bound on |clock offset| when neither the CEDDP nor --max-offset-ms gives one
DEFAULT_MAX_OFFSET_MS: Final = 50.0
#: a certificate expiring sooner than this is a warning
CERT_WARN_DAYS: Final = 30
#: the certificate files of Zenoh's ``transport/link/tls`` (the keys are not certificates)
CERT_KEYS: Final = ("root_ca_certificate", "connect_certificate", "listen_certificate")
#: the least the doctor listens, so that every robot's periodic report (0.5 s) can arrive
MIN_LISTEN_S: Final = 1.2


@dataclass(frozen=True)
class Check:
    level: str
    name: str
    message: str

    def line(self) -> str:
        return f"{self.level:<4} {self.name}: {self.message}"


@dataclass
class Observation:
    """What the doctor heard from the fleet while it listened."""

    fleet: str
    endpoints: tuple[str, ...]
    connect_s: float
    listened_s: float = 0.0
    ceddp_present: bool = False
    #: the CEDDP's last report, and how many came
    ceddp_stats: CeddpStats | None = None
    ceddp_reports: int = 0
    robots_present: set[str] = field(default_factory=set)
    #: each robot's last report
    robot_stats: dict[str, RobotStats] = field(default_factory=dict)
    #: fleets with a CEDDP on this router (to name the right one when --fleet is wrong)
    fleets_seen: set[str] = field(default_factory=set)
    decode_errors: int = 0
    #: per robot, the incarnations of its reports in the order they came (a change run once)
    report_order: dict[str, list[str]] = field(default_factory=dict)


# -- the rules ------------------------------------------------------------------------------------


def diagnose(obs: Observation, *, max_offset_ms: float | None = None) -> list[Check]:
    """Every check but the router's and the certificates', from what was heard.
    ``max_offset_ms``: the clock bound to apply (None: the CEDDP's, else 50 ms)."""
    checks = [ceddp_check(obs), robots_check(obs), versions_check(obs)]
    checks += [access_control_check(obs), qos_check(obs), delivery_check(obs)]
    checks += [sensors_check(obs), robot_ids_check(obs)]
    bound = max_offset_ms
    if bound is None and obs.ceddp_stats is not None:
        bound = obs.ceddp_stats.clock_max_offset_ms
    checks += clock_checks(obs, bound if bound is not None else DEFAULT_MAX_OFFSET_MS)
    return checks


def ceddp_check(obs: Observation) -> Check:
    stats = obs.ceddp_stats
    if stats is None:
        others = sorted(obs.fleets_seen - {obs.fleet})
        hint = (
            f"; this router has a CEDDP for fleet {', '.join(repr(f) for f in others)}: "
            "give --fleet"
            if others
            else "; is it running, and is --fleet the CEDDP's 'fleet' setting?"
        )
        where = "present but" if obs.ceddp_present else "not present and"
        return Check(
            FAIL,
            "ceddp",
            f"the CEDDP of fleet '{obs.fleet}' is {where} sent no CeddpStats on "
            f"{keys.ceddp_stats_key(obs.fleet)} within {obs.listened_s:.1f} s{hint}",
        )
    period = f"{obs.listened_s / obs.ceddp_reports:.1f} s" if obs.ceddp_reports else "?"
    latency = (
        f", p99 latency {stats.latency_ms_p99:.1f} ms"
        if stats.latency_ms_p99 is not None
        else ", no samples in its last interval"
    )
    return Check(
        OK,
        "ceddp",
        f"present and reporting (every {period}): CPU {stats.cpu_percent:.0f} %, ingest load "
        f"{stats.load:.0%}{latency}, {stats.processed} samples since start",
    )


def robots_check(obs: Observation) -> Check:
    present, reporting = obs.robots_present, set(obs.robot_stats)
    if not present and not reporting:
        return Check(WARN, "robots", f"no robot of fleet '{obs.fleet}' is present")
    silent = sorted(present - reporting)
    stopped = sorted(r for r, s in obs.robot_stats.items() if s.final)
    names = ", ".join(sorted(present | reporting))
    if silent:
        return Check(
            WARN,
            "robots",
            f"{len(present)} present ({names}); {', '.join(silent)} sent no stats within "
            f"{obs.listened_s:.1f} s (overloaded, or a different reliability mode?)",
        )
    if stopped:
        return Check(WARN, "robots", f"{names}: {', '.join(stopped)} stopped while listening")
    quiet = {r: s.silent_sensors for r, s in sorted(obs.robot_stats.items()) if s.silent_sensors}
    if quiet:
        which = "; ".join(f"{r}'s {', '.join(topics)}" for r, topics in quiet.items())
        return Check(
            WARN,
            "robots",
            f"{len(reporting)} present and reporting ({names}), but sensors give no reading: "
            f"{which} (see 'sensors')",
        )
    return Check(OK, "robots", f"{len(reporting)} present and reporting: {names}")


def _version(arpz: str, zenoh: str) -> str:
    return f"arpz {arpz or '?'}, Zenoh {zenoh or '?'}"


def versions_check(obs: Observation) -> Check:
    """Every robot's and the CEDDP's versions; a warning when they differ or are unknown."""
    seen: dict[str, tuple[str, str]] = {}
    if obs.ceddp_stats is not None:
        seen["CEDDP"] = (obs.ceddp_stats.arpz_version, obs.ceddp_stats.zenoh_version)
    for robot, stats in sorted(obs.robot_stats.items()):
        seen[robot] = (stats.arpz_version, stats.zenoh_version)
    if not seen:
        return Check(WARN, "versions", "nobody reported a version")
    unknown = sorted(name for name, (a, z) in seen.items() if not a or not z)
    distinct = set(seen.values())
    if len(distinct) == 1 and not unknown:
        arpz, zenoh = next(iter(distinct))
        return Check(OK, "versions", f"{', '.join(seen)} all run {_version(arpz, zenoh)}")
    listing = "; ".join(f"{name} {_version(*v)}" for name, v in seen.items())
    why = (
        f"{', '.join(unknown)} did not say (older than the doctor)"
        if unknown
        else "they differ: upgrade them together"
    )
    return Check(WARN, "versions", f"{listing}: {why}")


def access_control_check(obs: Observation) -> Check:
    stats = obs.ceddp_stats
    if stats is None or stats.access_control is None:
        return Check(WARN, "access control", "unknown: the CEDDP did not say (not reporting)")
    if stats.access_control:
        return Check(
            OK, "access control", "the CEDDP's Zenoh config enables access_control (deploy/)"
        )
    return Check(
        WARN,
        "access control",
        "not in force: the CEDDP's Zenoh config has no enabled access_control section, so any "
        "client that reaches the router may publish as a robot or send commands "
        "(docs/security.md)",
    )


def qos_check(obs: Observation) -> Check:
    lines = list(obs.ceddp_stats.incompatible_qos) if obs.ceddp_stats else []
    for robot, stats in sorted(obs.robot_stats.items()):
        lines += [f"{robot} (robot side): {line}" for line in stats.incompatible_qos]
    if lines:
        return Check(
            FAIL,
            "qos",
            f"INCOMPATIBLE_QOS, their data is refused: {'; '.join(lines[:6])}"
            + (f" (+{len(lines) - 6} more)" if len(lines) > 6 else ""),
        )
    return Check(OK, "qos", "no INCOMPATIBLE_QOS on the CEDDP or any robot")


def delivery_check(obs: Observation) -> Check:
    """Topics with deadline misses or loss, as their writers and the CEDDP count them (since
    each process started)."""
    problems: list[str] = []
    for robot, stats in sorted(obs.robot_stats.items()):
        for topic, c in sorted(stats.topics.items()):
            counts = {
                "deadline misses": c.deadline_missed,
                "confirmed lost (GAP)": c.gapped,
                "overwritten unacknowledged": c.overwritten_unacked,
                "writes refused": c.write_failures,
            }
            said = [f"{n} {what}" for what, n in counts.items() if n]
            if said:
                problems.append(f"{robot}/{topic}: {', '.join(said)}")
        for key, inbound in sorted(stats.inbound.items()):
            lost = inbound.lost + inbound.lifespan_expired
            if lost:
                problems.append(f"{robot} {key}: {lost} lost or expired on the way to the robot")
    if obs.ceddp_stats is not None:
        for rate in obs.ceddp_stats.topics:
            if rate.lost:
                problems.append(f"{rate.robot}/{rate.topic}: {rate.lost} lost at the CEDDP")
    if problems:
        more = f" (+{len(problems) - 8} more)" if len(problems) > 8 else ""
        return Check(WARN, "delivery", "; ".join(problems[:8]) + more)
    silent = sum(len(s.silent_sensors) for s in obs.robot_stats.values())
    topics = sum(len(s.topics) for s in obs.robot_stats.values()) - silent
    if silent:
        return Check(
            WARN,
            "delivery",
            f"no deadline misses or loss on {topics} topics; {silent} gave no reading to "
            "deliver (see 'sensors')",
        )
    return Check(OK, "delivery", f"no deadline misses or loss on {topics} topics")


def sensors_check(obs: Observation) -> Check:
    """Sensors with no reading for their robot's last interval (failed), and those whose
    driver raised, gave a refused value or read late since the robot started (warned)."""
    failed: list[str] = []
    warned: list[str] = []
    for robot, stats in sorted(obs.robot_stats.items()):
        for topic, c in sorted(stats.topics.items()):
            last = f"; last: {c.last_driver_error}" if c.last_driver_error else ""
            errors = (
                f"{c.driver_errors} reads of {c.produced} gave no reading "
                f"({c.driver_exceptions} raised, {c.values_refused} refused{last})"
                if c.driver_errors
                else ""
            )
            late = f"{c.late_reads} reads took longer than its period" if c.late_reads else ""
            said = ", ".join(x for x in (errors, late) if x)
            if topic in stats.silent_sensors:
                failed.append(
                    f"{robot}/{topic}: no reading for its last report interval"
                    + (f": {said}" if said else " (not read)")
                )
            elif said:
                warned.append(f"{robot}/{topic}: {said}")
    if failed or warned:
        lines = failed + warned
        more = f" (+{len(lines) - 6} more)" if len(lines) > 6 else ""
        return Check(FAIL if failed else WARN, "sensors", "; ".join(lines[:6]) + more)
    count = sum(len(s.topics) for s in obs.robot_stats.values())
    return Check(OK, "sensors", f"{count} sensors read without driver errors")


def robot_ids_check(obs: Observation) -> Check:
    """A robot id two processes run with: the CEDDP says so, or their reports came in turn."""
    found = list(obs.ceddp_stats.duplicate_robots) if obs.ceddp_stats else []
    seen = {line.split(":", 1)[0] for line in found}
    for robot, order in sorted(obs.report_order.items()):
        if robot not in seen and len(set(order)) < len(order):  # A, B, then A again
            found.append(f"{robot}: {', '.join(dict.fromkeys(order))} (reporting in turn)")
    if found:
        return Check(
            FAIL,
            "robot ids",
            f"two processes run with one robot_id: {'; '.join(found)}: the CEDDP drops the "
            "newer one's samples and both act on every command; stop one, and give each robot "
            "its own robot_id",
        )
    return Check(OK, "robot ids", "each robot id is used by one process")


def clock_checks(obs: Observation, bound_ms: float) -> list[Check]:
    """One line per robot: its clock offset to the CEDDP, failed beyond ``bound_ms``."""
    return [
        clock_check(obs.fleet, robot, stats, bound_ms)
        for robot, stats in sorted(obs.robot_stats.items())
    ]


def clock_check(fleet: str, robot: str, stats: RobotStats, bound_ms: float) -> Check:
    name = f"clock {robot}"
    clock = stats.clock
    if clock is None:
        return Check(
            WARN,
            name,
            "no clock offset reported (clock sync off, or an older robot): its latencies are "
            "measured on its own clock",
        )
    if clock.offset_ns is None or clock.delay_ns is None:
        return Check(
            WARN,
            name,
            f"no reply to {clock.requests} clock requests on {keys.ceddp_clock_key(fleet)} (an "
            "older CEDDP, or access control denies the query): latencies uncorrected",
        )
    offset_ms, delay_ms = clock.offset_ns / 1e6, clock.delay_ns / 1e6
    figures = (
        f"offset {offset_ms:+.1f} ms to the CEDDP (round trip {delay_ms:.1f} ms, best of "
        f"{clock.samples})"
    )
    # the truth is within offset +/- delay / 2: NTP is asked for only when certainly beyond
    if abs(offset_ms) - delay_ms / 2 > bound_ms:
        return Check(
            FAIL,
            name,
            f"{figures} exceeds the bound of {bound_ms:g} ms: set up NTP or chrony on the robot "
            "(the CEDDP corrects its latencies meanwhile)",
        )
    if abs(offset_ms) > bound_ms:
        return Check(
            WARN,
            name,
            f"{figures} may exceed the bound of {bound_ms:g} ms: its exchange's round trip is too "
            f"long to tell (the error is up to {delay_ms / 2:.1f} ms)",
        )
    return Check(OK, name, f"{figures}, within {bound_ms:g} ms")


# -- certificates ---------------------------------------------------------------------------------


class CertificateError(ArpzError):
    """A certificate file that cannot be read; the message says which and why."""


def certificate_expiry(path: str) -> datetime.datetime:
    """When the (first) certificate in the PEM file ``path`` expires, in UTC: read with the
    ``cryptography`` package when installed, else with ``openssl x509 -enddate``."""
    try:
        x509: Any = importlib.import_module("cryptography.x509")
    except ImportError:
        x509 = None
    if x509 is not None:
        try:
            cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
        except (OSError, ValueError) as exc:
            raise CertificateError(f"{path}: not a readable PEM certificate: {exc}") from None
        ends: datetime.datetime = cert.not_valid_after_utc
        return ends
    try:
        done = subprocess.run(
            ["openssl", "x509", "-enddate", "-noout", "-in", path],
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise CertificateError(
            f"{path}: cannot read its expiry (install the 'cryptography' package or openssl): {exc}"
        ) from None
    text = done.stdout.strip()
    if done.returncode != 0 or not text.startswith("notAfter="):
        reason = done.stderr.strip().splitlines()[0] if done.stderr.strip() else text
        raise CertificateError(f"{path}: not a readable PEM certificate: {reason}")
    stamp = text.removeprefix("notAfter=").replace("  ", " ")
    parsed = datetime.datetime.strptime(stamp, "%b %d %H:%M:%S %Y %Z")
    return parsed.replace(tzinfo=datetime.UTC)


def certificate_checks(
    files: dict[str, str],
    now: datetime.datetime,
    *,
    warn_days: int = CERT_WARN_DAYS,
    expiry: Callable[[str], datetime.datetime] = certificate_expiry,
) -> list[Check]:
    """One line per certificate file (``files``: Zenoh config key -> path)."""
    return [
        certificate_check(f"tls {what}", path, now, warn_days, expiry)
        for what, path in files.items()
    ]


def certificate_check(
    name: str,
    path: str,
    now: datetime.datetime,
    warn_days: int,
    expiry: Callable[[str], datetime.datetime],
) -> Check:
    try:
        ends = expiry(path)
    except CertificateError as exc:
        return Check(FAIL, name, str(exc))
    days = (ends - now).total_seconds() / 86400
    when = ends.strftime("%Y-%m-%d %H:%M UTC")
    if days < 0:
        return Check(FAIL, name, f"{path} expired on {when}: TLS sessions are refused")
    if days < warn_days:
        return Check(
            WARN,
            name,
            f"{path} expires on {when}, in {days:.0f} days: renew it "
            "(deploy/tls/make_fleet_certs.py)",
        )
    return Check(OK, name, f"{path} valid until {when} ({days:.0f} days)")


def tls_summary(obs: Observation, endpoints: Iterable[str], files: dict[str, str]) -> Check:
    """Whether this session and the CEDDP use TLS (the certificates get lines of their own)."""
    tls_endpoints = [e for e in endpoints if e.startswith(("tls/", "quic/"))]
    ceddp_tls = obs.ceddp_stats.tls if obs.ceddp_stats is not None else None
    said = {True: "the CEDDP reports TLS on", False: "the CEDDP reports TLS off", None: ""}[
        ceddp_tls
    ]
    if not tls_endpoints and not files:
        return Check(
            OK,
            "tls",
            "not used by this session (plain endpoints: traffic is not encrypted)"
            + (f"; {said}" if said else ""),
        )
    if tls_endpoints and not files:
        return Check(
            WARN,
            "tls",
            f"{', '.join(tls_endpoints)} with no certificate files in the Zenoh config "
            "(give --zenoh-config with root_ca_certificate)",
        )
    return Check(
        OK, "tls", f"{len(files)} certificate files checked" + (f"; {said}" if said else "")
    )


# -- I/O ------------------------------------------------------------------------------------------


class _Listener:
    """The fleet's reports and tokens, recorded by Zenoh callbacks (decode and store, under a
    lock, nothing that waits); ``observation`` copies them out."""

    def __init__(self, obs: Observation) -> None:
        self.obs = obs
        self.lock = threading.Lock()

    def on_robot_stats(self, key: str, payload: bytes, _attachment: bytes | None) -> None:
        parsed = keys.parse_robot_key(key)
        try:
            stats = STATS_DECODER.decode(payload)
        except DECODE_ERRORS:
            with self.lock:
                self.obs.decode_errors += 1
            return
        robot = parsed[0] if parsed else stats.robot
        with self.lock:
            self.obs.robot_stats[robot] = stats
            order = self.obs.report_order.setdefault(robot, [])
            if not stats.final and (not order or order[-1] != stats.incarnation):
                order.append(stats.incarnation)
                del order[:-16]

    def on_ceddp_stats(self, _key: str, payload: bytes, _attachment: bytes | None) -> None:
        try:
            stats = CEDDP_STATS_DECODER.decode(payload)
        except DECODE_ERRORS:
            with self.lock:
                self.obs.decode_errors += 1
            return
        with self.lock:
            self.obs.ceddp_stats = stats
            self.obs.ceddp_reports += 1

    def on_robot_presence(self, key: str, alive: bool) -> None:
        parsed = keys.parse_robot_key(key)
        if parsed is None:
            return
        with self.lock:
            if alive:
                self.obs.robots_present.add(parsed[0])
            else:
                self.obs.robots_present.discard(parsed[0])

    def on_ceddp_presence(self, key: str, alive: bool) -> None:
        parts = key.split("/")
        if len(parts) < 2 or not alive:
            return
        with self.lock:
            self.obs.fleets_seen.add(parts[1])
            if parts[1] == self.obs.fleet:
                self.obs.ceddp_present = True

    def complete(self) -> bool:
        """The CEDDP reported and every present robot did too, with its clock estimate when it
        measures one."""
        with self.lock:
            obs = self.obs
            return obs.ceddp_stats is not None and all(
                robot in obs.robot_stats and _settled(obs.robot_stats[robot])
                for robot in obs.robots_present
            )


def _settled(stats: RobotStats) -> bool:
    """A robot report worth judging: no clock sync, or an estimate already made."""
    return stats.clock is None or stats.clock.offset_ns is not None


def listen(transport: ZenohTransport, obs: Observation, timeout_s: float) -> Observation:
    """Listen until every present robot and the CEDDP reported (at least ``MIN_LISTEN_S``, at
    most ``timeout_s``)."""
    listener = _Listener(obs)
    fleet = obs.fleet
    transport.subscribe(keys.all_stats(fleet), listener.on_robot_stats)
    transport.subscribe(keys.ceddp_stats_key(fleet), listener.on_ceddp_stats)
    transport.watch_liveliness(keys.all_presence(fleet), listener.on_robot_presence)
    transport.watch_liveliness(f"{keys.ROOT}/*/ceddp/presence", listener.on_ceddp_presence)
    start = time.monotonic()
    end = start + max(timeout_s, MIN_LISTEN_S)
    while time.monotonic() < end:
        if time.monotonic() - start >= MIN_LISTEN_S and listener.complete():
            break
        time.sleep(0.05)
    with listener.lock:  # a copy: callbacks may still come until the session is closed
        obs.listened_s = time.monotonic() - start
        return dataclasses.replace(
            obs,
            robots_present=set(obs.robots_present),
            robot_stats=dict(obs.robot_stats),
            fleets_seen=set(obs.fleets_seen),
            report_order={r: list(order) for r, order in obs.report_order.items()},
        )


def certificate_files(config_file: str | None) -> dict[str, str]:
    """The certificate files the session's Zenoh config names (key -> path)."""
    if not config_file:
        return {}
    if not Path(config_file).is_file():
        raise ArpzError(f"--zenoh-config {config_file}: no such file")
    conf = load_zenoh_config(config_file, source="--zenoh-config")
    files = {}
    for key in CERT_KEYS:
        value = config_value(conf, f"transport/link/tls/{key}")
        if isinstance(value, str):
            files[key] = value
    return files


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m arpz doctor",
        description="Check a running fleet and say what is wrong: router, versions, TLS "
        "certificates, access control, QoS, delivery, clock offsets (docs/tools.md).",
    )
    add_version_option(parser)
    add_fleet_client_options(parser)
    parser.add_argument(
        "--timeout",
        type=float,
        default=5.0,
        metavar="S",
        help="how long to try to reach the router, and the most to listen (default 5)",
    )
    parser.add_argument(
        "--max-offset-ms",
        type=float,
        default=None,
        metavar="MS",
        help="the clock offset bound (default: the CEDDP's [clock] max_offset_ms, else 50)",
    )
    add_json_option(parser, "the checks and what the fleet reported")
    return parser


def report(checks: list[Check], obs: Observation | None, code: int) -> dict[str, Any]:
    """The ``--json`` document."""
    robots: dict[str, Any] = {}
    if obs is not None:
        for robot, stats in sorted(obs.robot_stats.items()):
            clock = stats.clock
            robots[robot] = {
                "arpz_version": stats.arpz_version,
                "zenoh_version": stats.zenoh_version,
                "mode": stats.mode,
                "clock_offset_ms": None
                if clock is None or clock.offset_ns is None
                else clock.offset_ns / 1e6,
                "clock_delay_ms": None
                if clock is None or clock.delay_ns is None
                else clock.delay_ns / 1e6,
                "incarnation": stats.incarnation,
                "silent_sensors": list(stats.silent_sensors),
                "driver_errors": {t: c.driver_errors for t, c in stats.topics.items()},
            }
    ceddp = msgspec.to_builtins(obs.ceddp_stats) if obs and obs.ceddp_stats else None
    return {
        "exit_code": code,
        "checks": [{"level": c.level, "check": c.name, "message": c.message} for c in checks],
        "robots": robots,
        "ceddp": ceddp,
    }


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        endpoints = connect_endpoints(args.connect)
        keys.check_chunk(args.fleet, what="--fleet")
        if not args.timeout > 0:
            raise ArpzError("--timeout must be > 0 seconds")
        if args.max_offset_ms is not None and not args.max_offset_ms > 0:
            raise ArpzError("--max-offset-ms must be > 0")
        files = certificate_files(args.zenoh_config)
    except ArpzError as exc:
        return fail(TOOL, str(exc))
    now = datetime.datetime.now(datetime.UTC)
    cert_checks = certificate_checks(files, now)
    settings = SessionSettings(mode="client", connect=endpoints, config_file=args.zenoh_config)
    started = time.monotonic()
    try:
        transport = ZenohTransport.open(settings, timeout_s=args.timeout)
    except TransportError as exc:
        checks = [Check(FAIL, "router", str(exc)), *cert_checks]
        return finish(checks, None, args.json)
    connect_s = time.monotonic() - started
    try:
        obs = listen(
            transport, Observation(args.fleet, endpoints, connect_s), args.timeout - connect_s
        )
    finally:
        transport.close()
    router = Check(
        OK,
        "router",
        f"reached {', '.join(endpoints)} in {connect_s:.2f} s; listened {obs.listened_s:.1f} s "
        f"to fleet '{args.fleet}'",
    )
    checks = [router, *diagnose(obs, max_offset_ms=args.max_offset_ms)]
    checks.insert(4, tls_summary(obs, endpoints, files))
    checks[5:5] = cert_checks
    return finish(checks, obs, args.json)


def finish(checks: list[Check], obs: Observation | None, json_target: str | None) -> int:
    code = 1 if any(c.level == FAIL for c in checks) else 0
    if json_target != "-":
        for check in checks:
            print(check.line())
        failed = sum(c.level == FAIL for c in checks)
        warned = sum(c.level == WARN for c in checks)
        print(
            f"{len(checks)} checks: {failed} failed, {warned} warnings"
            if failed or warned
            else f"{len(checks)} checks: all well"
        )
        sys.stdout.flush()
    emit_json(report(checks, obs, code), json_target)
    return code


if __name__ == "__main__":
    sys.exit(main())
