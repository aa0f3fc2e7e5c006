"""``python -m arpz demo``: a CEDDP and N robots as real processes on loopback.

The demo writes real TOML configs, starts ``python -m arpz.ceddp`` and ``python -m arpz.robot``
exactly as a user would on a server and on robots, runs them, stops them with SIGINT (the
clean path), then prints the reconciled summary and the path of the ``.rrd``. Any part that
fails (a process that does not start, does not stop, exits non-zero, or never reports) makes
the demo exit non-zero with a message that says which and where its log is.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

PRESET_CYCLE = ("machine1", "machine2", "machine3")


class DemoError(RuntimeError):
    pass


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class Proc:
    name: str
    popen: subprocess.Popen[str]
    log_path: Path
    lines: list[str] = field(default_factory=list)
    _log: TextIO | None = None
    _reader: threading.Thread | None = None

    def start_reader(self) -> None:
        self._log = self.log_path.open("w", encoding="utf-8")

        def pump() -> None:
            assert self.popen.stdout is not None and self._log is not None
            with self.popen.stdout, self._log:
                for line in self.popen.stdout:
                    self.lines.append(line)
                    self._log.write(line)
                    self._log.flush()

        self._reader = threading.Thread(target=pump, name=f"log-{self.name}", daemon=True)
        self._reader.start()

    def wait_line(self, needle: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if any(needle in line for line in self.lines):
                return
            if self.popen.poll() is not None:
                break
            time.sleep(0.02)
        raise DemoError(
            f"{self.name} did not become ready within {timeout_s:.0f} s "
            f"(exit code {self.popen.poll()}); see {self.log_path}:\n{self.tail()}"
        )

    def stop(self, timeout_s: float) -> int:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGINT)
        try:
            return self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            self.popen.wait()
            raise DemoError(
                f"{self.name} did not stop within {timeout_s:.0f} s of SIGINT and "
                f"was killed; see {self.log_path}"
            ) from None

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait()
        if self._reader is not None:
            self._reader.join(timeout=10)

    def tail(self, n: int = 15) -> str:
        return "".join(self.lines[-n:])


def _spawn(name: str, args: list[str], workdir: Path) -> Proc:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    popen = subprocess.Popen(
        [sys.executable, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=workdir,
        env=env,
    )
    proc = Proc(name, popen, workdir / f"{name}.log")
    proc.start_reader()
    return proc


def write_configs(
    workdir: Path,
    *,
    robots: int,
    port: int,
    fleet: str,
    rrd: Path,
    rate_hz: float,
    hello_rate_hz: float,
    local_cache: bool,
    cache_control: bool,
    rmax_hz: float = 0.0,
) -> tuple[Path, list[Path]]:
    endpoint = f"tcp/127.0.0.1:{port}"
    relay = f'relay = "robot{robots}"' if robots > 1 else ""
    ceddp = workdir / "ceddp.toml"
    ceddp.write_text(
        f'fleet = "{fleet}"\nlisten = ["{endpoint}"]\nrrd = "{rrd.as_posix()}"\n'
        f'summary_json = "summary.json"\ncache_control = {str(cache_control).lower()}\n'
        f"\n[hello]\n{relay}\n"
        + (f"\n[qos]\nenabled = true\nrmax_hz = {rmax_hz}\n" if rmax_hz > 0 else ""),
        encoding="utf-8",
    )
    robot_files = []
    for index in range(1, robots + 1):
        path = workdir / f"robot{index}.toml"
        hello = f"\n[hello]\nenabled = true\nrate_hz = {hello_rate_hz}\n" if index == 1 else ""
        path.write_text(
            f'robot_id = "robot{index}"\nfleet = "{fleet}"\nconnect = ["{endpoint}"]\n'
            f'preset = "{PRESET_CYCLE[(index - 1) % 3]}"\npreset_rate_hz = {rate_hz}\n'
            f"seed = {index}\n\n[local_cache]\nenabled = {str(local_cache).lower()}\n{hello}",
            encoding="utf-8",
        )
        robot_files.append(path)
    return ceddp, robot_files


def run_demo(
    *,
    robots: int,
    duration_s: float,
    rrd: Path,
    rate_hz: float,
    hello_rate_hz: float,
    local_cache: bool,
    cache_control: bool,
    workdir: Path,
    rmax_hz: float = 0.0,
    progress: TextIO = sys.stderr,
) -> dict[str, Any]:
    """Run the fleet and return the CEDDP's summary; raise DemoError when a part failed."""
    fleet = "demo"
    ceddp_toml, robot_tomls = write_configs(
        workdir,
        robots=robots,
        port=free_port(),
        fleet=fleet,
        rrd=rrd,
        rate_hz=rate_hz,
        hello_rate_hz=hello_rate_hz,
        local_cache=local_cache,
        cache_control=cache_control,
        rmax_hz=rmax_hz,
    )
    procs: list[Proc] = []
    try:
        ceddp = _spawn("ceddp", ["-m", "arpz.ceddp", "--config", str(ceddp_toml)], workdir)
        procs.append(ceddp)
        ceddp.wait_line("ready on", timeout_s=30)
        # the Hello relay (the last robot) is up before the others: a Hello sent before its
        # relay joined cannot be relayed (the CEDDP counts it as no_relay)
        relay = _spawn(
            robot_tomls[-1].stem, ["-m", "arpz.robot", "--config", str(robot_tomls[-1])], workdir
        )
        procs.append(relay)
        relay.wait_line("running", timeout_s=30)
        others = [
            _spawn(path.stem, ["-m", "arpz.robot", "--config", str(path)], workdir)
            for path in robot_tomls[:-1]
        ]
        procs.extend(others)
        for proc in others:
            proc.wait_line("running", timeout_s=30)
        fleet_procs = [*others, relay]
        print(f"demo: CEDDP and {robots} robots running; logs in {workdir}", file=progress)
        start = time.monotonic()
        while (elapsed := time.monotonic() - start) < duration_s:
            for proc in procs:
                if proc.popen.poll() is not None:
                    raise DemoError(
                        f"{proc.name} exited early with code {proc.popen.returncode};"
                        f" see {proc.log_path}:\n{proc.tail()}"
                    )
            print(f"\rdemo: {elapsed:5.1f}/{duration_s:.0f} s", end="", file=progress, flush=True)
            time.sleep(min(0.5, duration_s - elapsed))
        print(f"\rdemo: {duration_s:5.1f}/{duration_s:.0f} s, stopping", file=progress)
        failures = []
        for proc in fleet_procs:
            code = proc.stop(timeout_s=15)
            if code != 0:
                failures.append(f"{proc.name} exited with code {code}; see {proc.log_path}")
        code = ceddp.stop(timeout_s=30)
        if code != 0:
            failures.append(f"ceddp exited with code {code}; see {ceddp.log_path}")
        summary_path = workdir / "summary.json"
        if not summary_path.exists():
            failures.append(f"the CEDDP wrote no summary ({summary_path})")
            raise DemoError("; ".join(failures))
        summary: dict[str, Any] = json.loads(summary_path.read_text(encoding="utf-8"))
        failures += check_summary(summary, robots)
        if failures:
            print(format_summary(summary), file=progress)
            raise DemoError("; ".join(failures))
        return summary
    finally:
        for proc in procs:
            proc.kill()


def check_summary(summary: dict[str, Any], robots: int) -> list[str]:
    """What a healthy demo must show: every robot reported, counts reconcile, Hellos came back."""
    problems = []
    for index in range(1, robots + 1):
        name = f"robot{index}"
        row = summary["robots"].get(name)
        if row is None:
            problems.append(f"{name} never reached the CEDDP")
            continue
        if not row["final_stats"]:
            problems.append(f"{name}'s final report did not reach the CEDDP")
        if row["produced"] != row["sent"] + row["held_back"]:
            problems.append(
                f"{name}: produced {row['produced']} != sent {row['sent']} + held "
                f"back {row['held_back']}"
            )
        if row["sent"] != row["received"] + row["lost"]:
            problems.append(
                f"{name}: sent {row['sent']} != received {row['received']} + lost {row['lost']}"
            )
    hello = summary["robots"].get("robot1", {}).get("hello") or {}
    if not hello.get("received"):
        problems.append("no Hello came back to robot1")
    return problems


def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)


def format_summary(summary: dict[str, Any]) -> str:
    headers = [
        "robot",
        "produced",
        "sent",
        "held back",
        "received",
        "cc discarded",
        "lost",
        "lat p50 ms",
        "lat p99 ms",
    ]
    rows = [
        [
            name,
            *(
                _fmt(r[k])
                for k in (
                    "produced",
                    "sent",
                    "held_back",
                    "received",
                    "cc_discarded",
                    "lost",
                    "latency_ms_p50",
                    "latency_ms_p99",
                )
            ),
        ]
        for name, r in sorted(summary["robots"].items())
    ]
    widths = [
        max(len(h), *(len(row[i]) for row in rows)) if rows else len(h)
        for i, h in enumerate(headers)
    ]
    lines = ["  ".join(h.rjust(w) for h, w in zip(headers, widths, strict=True))]
    lines += ["  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) for row in rows]
    for name, r in sorted(summary["robots"].items()):
        hello = r.get("hello")
        if hello and hello.get("sent"):
            lines.append(
                f"Hello {name} -> CEDDP -> relay -> CEDDP -> {name}: sent {hello['sent']}, "
                f"back {hello['received']}, lost {hello['lost']}"
                f" ({summary['hello_relay']['no_relay']} before the relay joined), "
                f"late {hello['late']}, "
                f"round trip p50 {_fmt(hello['rtt_ms_p50'])} ms, p99 {_fmt(hello['rtt_ms_p99'])} ms"
            )
    qos = summary.get("qos")
    if qos:
        for assignment in qos["assignments"]:
            robots = assignment["robots"]
            first = next(iter(robots.values()))
            lines.append(
                f"QoS epoch {assignment['epoch']} ({assignment['reason']}): "
                f"T_avg {assignment['t_avg']:.3f}, R {first['rate_hz']:.2f} Hz "
                f"(deadline {first['deadline_s'] * 1000:.1f} ms), D {first['depth']} "
                f"for {', '.join(robots)}"
            )
        acks = ", ".join(
            f"{robot} {ack['status']} epoch {ack['epoch']}" for robot, ack in qos["acks"].items()
        )
        lines.append(f"QoS acknowledgements: {acks or 'none'}")
        for error in qos["errors"]:
            lines.append(f"QoS error: {error}")
    ingest = summary["ingest"]
    lines.append(
        f"CEDDP: {ingest['processed']} samples ingested, "
        f"{ingest['unknown_keys']} on unknown keys, "
        f"{summary['dashboard']['dropped']} dashboard frames dropped"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m arpz demo", description=__doc__)
    parser.add_argument("--robots", type=int, default=3)
    parser.add_argument("--duration", type=float, default=10.0, help="seconds of running")
    parser.add_argument("--rrd", type=Path, default=Path("arpz-demo.rrd"))
    parser.add_argument("--rate", type=float, default=50.0, help="sensor rate (Hz)")
    parser.add_argument("--hello-rate", type=float, default=10.0, help="Hello rate (Hz)")
    parser.add_argument("--no-local-cache", action="store_true")
    parser.add_argument("--no-cache-control", action="store_true")
    parser.add_argument(
        "--rmax", type=float, default=500.0, help="QoS balancing: Rmax (Hz) of seed 001 eq. 4"
    )
    parser.add_argument("--no-qos", action="store_true", help="keep --rate, no QoS optimiser")
    parser.add_argument("--workdir", type=Path, help="where configs and logs go (default: temp)")
    parser.add_argument("--json", type=Path, help="also write the summary here")
    args = parser.parse_args(argv)
    if args.robots < 1 or args.duration <= 0 or args.rate <= 0:
        print("demo: --robots must be >= 1, --duration and --rate > 0", file=sys.stderr)
        return 2
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="arpz-demo-"))
    workdir.mkdir(parents=True, exist_ok=True)
    rrd = args.rrd.resolve()
    try:
        summary = run_demo(
            robots=args.robots,
            duration_s=args.duration,
            rrd=rrd,
            rate_hz=args.rate,
            hello_rate_hz=args.hello_rate,
            local_cache=not args.no_local_cache,
            cache_control=not args.no_cache_control,
            workdir=workdir,
            rmax_hz=0.0 if args.no_qos else args.rmax,
        )
    except DemoError as exc:
        print(f"demo FAILED: {exc}", file=sys.stderr)
        return 1
    print(format_summary(summary))
    print(f"Rerun recording: {rrd}  (open it with: rerun {rrd})")
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2), encoding="utf-8")
    return 0
