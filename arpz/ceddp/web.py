"""The CEDDP's web view: a fleet status page, its JSON, and Prometheus metrics (``web_port``).

``/`` is one HTML page with its CSS and JavaScript inline (a fleet's server often has no route
to a CDN), which polls ``/api/status`` every second and redraws. ``/api/status`` is the JSON of
``arpz.ceddp.status.FleetStatus``. ``/metrics`` is the Prometheus text exposition of the same
state, made by prometheus-client from a custom collector: the numbers are read from the CEDDP
when Prometheus scrapes, never kept twice (docs/tools.md "Live views" lists the names).

The server is the standard library's ``ThreadingHTTPServer`` on a daemon thread: a status page
serves a few requests a second, each of which copies a snapshot and formats it, so a framework
would add a dependency and nothing else. A request never touches the ingest beyond the
snapshot's short copy under its lock. This is the only module of arpz that imports
prometheus_client (an import-linter contract in pyproject.toml).
"""

from __future__ import annotations

import errno
import logging
import threading
from collections.abc import Callable, Iterable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import msgspec
from prometheus_client import CONTENT_TYPE_LATEST, ProcessCollector, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector, CollectorRegistry

from arpz.ceddp.status import FleetStatus, RobotStatus, TopicStatus
from arpz.core.errors import ConfigError
from arpz.core.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
throttled = ThrottledLog(log)

#: (metric name, help, TopicStatus field) of the per-topic counters
TOPIC_COUNTERS: tuple[tuple[str, str, str], ...] = (
    ("arpz_samples_received", "Sensor samples the CEDDP received", "received"),
    ("arpz_samples_lost", "Sensor samples lost (sequence gaps, before the CEDDP joined)", "lost"),
    ("arpz_received_bytes", "Sensor payload bytes the CEDDP received", "bytes"),
    ("arpz_decode_errors", "Sensor samples that could not be decoded", "decode_errors"),
    (
        "arpz_cache_control_discarded",
        "Unchanged readings cache control kept from planning",
        "cc_discarded",
    ),
    ("arpz_robot_samples_sent", "Samples the robot reports it sent", "sent"),
    ("arpz_robot_held_back", "Readings the robot's local cache held back", "held_back"),
    (
        "arpz_robot_retransmitted",
        "Resends by the robot's reliable channel (NACKed samples)",
        "retransmitted",
    ),
    ("arpz_robot_gapped", "Samples the robot answered with GAP (NACKed too late: lost)", "gapped"),
    ("arpz_robot_deadline_missed", "Offered-deadline misses the robot reports", "deadline_missed"),
    ("arpz_robot_write_failures", "Readings the robot's full history refused", "write_failures"),
    (
        "arpz_robot_driver_errors",
        "Reads of the sensor's driver that gave no reading (it raised, or its value was refused)",
        "driver_errors",
    ),
    ("arpz_robot_late_reads", "Reads that took longer than the sensor's period", "late_reads"),
)
#: (metric name, help, TopicStatus field, scale) of the per-topic gauges of the last interval
TOPIC_GAUGES: tuple[tuple[str, str, str, float], ...] = (
    (
        "arpz_receive_rate_hz",
        "Samples received per second, over the last 2 s or more (since an earlier read)",
        "rate_hz",
        1.0,
    ),
    (
        "arpz_receive_bytes_per_second",
        "Bytes received per second, over the last 2 s or more",
        "bytes_per_s",
        1.0,
    ),
    (
        "arpz_last_sample_age_seconds",
        "Seconds since the topic's last sample arrived",
        "last_sample_age_s",
        1.0,
    ),
    (
        "arpz_robot_sensor_silent",
        "1 while the sensor gave no reading for the robot's whole last reporting interval",
        "silent",
        1.0,
    ),
)
#: (metric name, help, PreviousIncarnations field) of the counters of a robot's earlier
#: incarnations, summed (a restart starts the per-topic counters again from zero)
PREVIOUS_COUNTERS: tuple[tuple[str, str, str], ...] = (
    (
        "arpz_robot_previous_samples_received",
        "Samples the CEDDP received from the robot's earlier incarnations",
        "received",
    ),
    (
        "arpz_robot_previous_samples_lost",
        "Samples of the robot's earlier incarnations lost",
        "lost",
    ),
    (
        "arpz_robot_previous_samples_sent",
        "Samples the robot's earlier incarnations reported sent",
        "sent",
    ),
    (
        "arpz_robot_previous_driver_errors",
        "Driver errors the robot's earlier incarnations reported",
        "driver_errors",
    ),
)
#: (metric name, help, RobotStatus field, scale) of the per-robot gauges
ROBOT_GAUGES: tuple[tuple[str, str, str, float], ...] = (
    ("arpz_robot_cpu_ratio", "CPU of the robot agent, share of one core", "cpu_percent", 0.01),
    (
        "arpz_robot_qos_epoch",
        "Epoch of the CEDDP QoS assignment the robot runs (0: none)",
        "qos_epoch",
        1.0,
    ),
    ("arpz_robot_qos_rate_hz", "QoS rate R the robot runs (Hz)", "qos_rate_hz", 1.0),
    ("arpz_robot_qos_depth", "QoS history depth D the robot runs (samples)", "qos_depth", 1.0),
    (
        "arpz_robot_clock_offset_seconds",
        "Clock offset of the robot to the CEDDP, as the clock check measures it",
        "clock_offset_ms",
        0.001,
    ),
    (
        "arpz_robot_clock_delay_seconds",
        "Round trip of the clock-offset exchange",
        "clock_delay_ms",
        0.001,
    ),
)


class StatusCollector(Collector):
    """prometheus-client collector over ``read()``: called on every scrape, so what Prometheus
    gets is the CEDDP's state at that moment (counters) or its last interval (gauges)."""

    def __init__(self, read: Callable[[], FleetStatus]) -> None:
        self._read = read

    def collect(self) -> Iterable[Metric]:
        status = self._read()
        yield from _topic_metrics(status.robots)
        yield from _robot_metrics(status.robots)
        yield from _ceddp_metrics(status)


def _topic_metrics(robots: list[RobotStatus]) -> Iterable[Metric]:
    labels = ["robot", "topic"]
    rows: list[tuple[RobotStatus, TopicStatus]] = [(r, t) for r in robots for t in r.topics]
    for name, text, field in TOPIC_COUNTERS:
        counter = CounterMetricFamily(name, text, labels=labels)
        for robot, topic in rows:
            counter.add_metric([robot.robot, topic.topic], getattr(topic, field))
        yield counter
    for name, text, field, scale in TOPIC_GAUGES:
        gauge = GaugeMetricFamily(name, text, labels=labels)
        for robot, topic in rows:
            value = getattr(topic, field)
            if value is not None:
                gauge.add_metric([robot.robot, topic.topic], value * scale)
        yield gauge
    quantiles = (
        (
            "arpz_latency_seconds",
            "Robot stamp to CEDDP arrival over the last interval",
            (("0.5", "latency_ms_p50"), ("0.99", "latency_ms_p99")),
        ),
        (
            "arpz_staleness_seconds",
            "How long the CEDDP held a value older than the robot's reading, last interval",
            (("0.99", "staleness_ms_p99"),),
        ),
    )
    for name, text, fields in quantiles:
        gauge = GaugeMetricFamily(name, text, labels=[*labels, "quantile"])
        for robot, topic in rows:
            for q, field in fields:
                value = getattr(topic, field)
                if value is not None:
                    gauge.add_metric([robot.robot, topic.topic, q], value / 1000)
        yield gauge


def _robot_metrics(robots: list[RobotStatus]) -> Iterable[Metric]:
    up = GaugeMetricFamily(
        "arpz_robot_up", "1 while the robot's presence token is seen", labels=["robot"]
    )
    for robot in robots:
        up.add_metric([robot.robot], 1.0 if robot.alive else 0.0)
    yield up
    for name, text, field, scale in ROBOT_GAUGES:
        gauge = GaugeMetricFamily(name, text, labels=["robot"])
        for robot in robots:
            value = getattr(robot, field)
            if value is not None:
                gauge.add_metric([robot.robot], value * scale)
        yield gauge
    info = GaugeMetricFamily(
        "arpz_robot_incarnation_info",
        "The robot's incarnation whose counters are shown (a restart is a new one)",
        labels=["robot", "incarnation"],
    )
    earlier = GaugeMetricFamily(
        "arpz_robot_previous_incarnations",
        "Earlier incarnations of the robot (restarts, or a second process with its id)",
        labels=["robot"],
    )
    duplicates = GaugeMetricFamily(
        "arpz_robot_duplicate_processes",
        "Other processes running with the robot's id now (their samples are dropped)",
        labels=["robot"],
    )
    dropped = CounterMetricFamily(
        "arpz_robot_duplicate_dropped",
        "Samples of another process with the robot's id, dropped",
        labels=["robot"],
    )
    for robot in robots:
        if robot.incarnation is not None:
            info.add_metric([robot.robot, robot.incarnation], 1.0)
        earlier.add_metric([robot.robot], robot.previous.incarnations)
        duplicates.add_metric([robot.robot], len(robot.duplicates))
        dropped.add_metric([robot.robot], robot.duplicate_dropped)
    yield from (info, earlier, duplicates, dropped)
    for name, text, field in PREVIOUS_COUNTERS:
        counter = CounterMetricFamily(name, text, labels=["robot"])
        for robot in robots:
            counter.add_metric([robot.robot], getattr(robot.previous, field))
        yield counter
    rtt = GaugeMetricFamily(
        "arpz_robot_hello_rtt_seconds",
        "Hello round trip (four hops through the CEDDP)",
        labels=["robot", "quantile"],
    )
    for robot in robots:
        if robot.hello_rtt_ms_p50 is not None:
            rtt.add_metric([robot.robot, "0.5"], robot.hello_rtt_ms_p50 / 1000)
    yield rtt


def _ceddp_metrics(status: FleetStatus) -> Iterable[Metric]:
    ceddp = status.ceddp
    yield CounterMetricFamily(
        "arpz_ceddp_samples_processed",
        "Sensor samples the CEDDP's ingest took",
        value=ceddp.processed,
    )
    for name, text, value in (
        (
            "arpz_ceddp_cpu_ratio",
            "CPU of the CEDDP process over the last interval, share of one core",
            None if ceddp.cpu_percent is None else ceddp.cpu_percent / 100,
        ),
        (
            "arpz_ceddp_ingest_load_ratio",
            "Share of the last interval the sensor path worked",
            ceddp.ingest_load,
        ),
        (
            "arpz_ceddp_ingest_backlog_seconds",
            "Longest a sample waited before the sensor path took it, last interval",
            None if ceddp.ingest_backlog_ms is None else ceddp.ingest_backlog_ms / 1000,
        ),
        (
            "arpz_ceddp_capacity_hz",
            "Measured ingest capacity, samples per busy second",
            ceddp.capacity_hz,
        ),
        (
            "arpz_ceddp_budget_hz",
            "Fleet rate budget of the overload governor, samples/s",
            ceddp.budget_hz,
        ),
    ):
        if value is not None:
            yield GaugeMetricFamily(name, text, value=value)
    channel = ceddp.channel
    if channel is not None:
        for field, text in (
            ("delivered", "Samples the CEDDP's reliable reader delivered"),
            ("lost", "Samples the CEDDP's reliable reader declared lost"),
            ("retransmitted", "Delivered samples that arrived by retransmission"),
            ("nacks", "ACKNACKs the CEDDP's reader sent asking for samples"),
            ("gaps", "GAPs the CEDDP's reader received (samples no longer held)"),
            ("deadline_missed", "Requested-deadline misses of the CEDDP's reader"),
        ):
            yield CounterMetricFamily(
                f"arpz_ceddp_channel_{field}", text, value=getattr(channel, field)
            )
        yield GaugeMetricFamily(
            "arpz_ceddp_channel_matched", "Writers the reader matches now", value=channel.matched
        )
    dropped = CounterMetricFamily(
        "arpz_live_view_dropped",
        "Frames a live view dropped because it fell behind",
        labels=["view"],
    )
    for view, count in sorted(status.views_dropped.items()):
        dropped.add_metric([view], count)
    yield dropped


def registry_for(read: Callable[[], FleetStatus]) -> CollectorRegistry:
    """A registry of its own (never the global one): the fleet's metrics and the process's."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(StatusCollector(read))
    ProcessCollector(registry=registry)
    return registry


class StatusWeb:
    """Serves ``/``, ``/api/status`` and ``/metrics`` on ``host:port`` from a daemon thread.
    The port is bound in the constructor, so a port in use fails the CEDDP's start at once."""

    def __init__(self, read: Callable[[], FleetStatus], *, host: str, port: int) -> None:
        self.read = read
        self.registry = registry_for(read)
        handler = _handler_for(self)
        try:
            self._httpd = ThreadingHTTPServer((host, port), handler)
        except OSError as exc:
            why = "in use by another process" if exc.errno == errno.EADDRINUSE else exc.strerror
            raise ConfigError(
                f"web_port {port} on {host} cannot be served: {why}; choose another web_port "
                "(or 0 to turn the status page off)"
            ) from None
        self._httpd.daemon_threads = True
        self.port = int(self._httpd.server_address[1])
        self._thread = threading.Thread(
            target=self._httpd.serve_forever, name="arpz-web", daemon=True
        )

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        if self._thread.is_alive():
            self._httpd.shutdown()
        self._httpd.server_close()

    def status_json(self) -> bytes:
        return msgspec.json.encode(self.read())

    def metrics_text(self) -> bytes:
        return generate_latest(self.registry)


def _handler_for(web: StatusWeb) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        server_version = "arpz-ceddp"

        def do_GET(self) -> None:
            path = self.path.split("?", 1)[0]
            try:
                if path in ("/", "/index.html"):
                    self._send(200, "text/html; charset=utf-8", PAGE.encode())
                elif path == "/api/status":
                    self._send(200, "application/json", web.status_json())
                elif path == "/metrics":
                    self._send(200, CONTENT_TYPE_LATEST, web.metrics_text())
                else:
                    self._send(404, "text/plain; charset=utf-8", b"not found: try / or /metrics\n")
            except (BrokenPipeError, ConnectionResetError):
                pass  # the client went away: nothing to answer
            except Exception:  # a bug in one request must not stop the page
                throttled.exception(f"web {path}", "status page request %s failed", path)
                self._send(500, "text/plain; charset=utf-8", b"internal error (see the log)\n")

        def _send(self, code: int, content_type: str, body: bytes) -> None:
            self.send_response(code)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, format: str, *args: object) -> None:
            log.debug("web: " + format, *args)

    return Handler


#: the status page: no external resource (the server may have no network), redrawn from
#: /api/status every second
PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>arpz fleet status</title>
<style>
body{font:14px/1.4 system-ui,sans-serif;margin:0;background:#f6f7f9;color:#1d2330}
header{background:#1d2330;color:#fff;padding:10px 18px;display:flex;gap:22px;align-items:baseline;
flex-wrap:wrap}
header h1{font-size:18px;margin:0}header a{color:#9cc8ff}
main{padding:12px 18px}
.cards{display:flex;gap:10px;flex-wrap:wrap;margin-bottom:12px}
.card{background:#fff;border:1px solid #dde1e8;border-radius:6px;padding:6px 12px;min-width:110px}
.card b{display:block;font-size:18px}
table{border-collapse:collapse;background:#fff;width:100%;margin-bottom:14px;font-size:13px}
th,td{border:1px solid #dde1e8;padding:3px 7px;text-align:right;white-space:nowrap}
th{background:#eef1f5;font-weight:600;white-space:normal;vertical-align:bottom}
td:first-child,th:first-child,td.l{text-align:left}.scroll{overflow-x:auto}
.up{color:#12813a;font-weight:600}.down{color:#b3261e;font-weight:600}
.warn{background:#fff4d6}.bad{background:#fde2e0}
h2{font-size:15px;margin:14px 0 6px}small{color:#667}
</style></head>
<body>
<header><h1>arpz fleet <span id="fleet">…</span></h1>
<span>updated <span id="updated">never</span> (<span id="polls">0</span> refreshes)</span>
<span id="links"><a href="/api/status">/api/status</a> · <a href="/metrics">/metrics</a></span>
<span id="error"></span></header>
<main>
<div class="cards" id="cards"></div>
<h2>Robots</h2>
<div class="scroll"><table id="robots"><thead><tr><th>robot</th><th>state</th>
<th>QoS epoch</th><th>R (Hz)</th>
<th>D</th><th>rate (Hz)</th><th>received</th><th>lost</th><th>loss</th><th>sent</th>
<th>retransmitted</th><th>gapped</th><th>deadline misses</th><th>latency p99 (ms)</th>
<th>staleness p99 (ms)</th><th>last sample (s ago)</th><th>clock offset (ms)</th>
<th>clock delay (ms)</th><th>CPU %</th><th>driver errors</th><th>silent sensors</th>
<th>incarnation</th><th>earlier incarnations</th></tr></thead><tbody></tbody></table></div>
<h2>Topics</h2>
<div class="scroll"><table id="topics"><thead><tr><th>robot / topic</th><th>kind</th>
<th>rate (Hz)</th><th>received</th><th>lost</th><th>retransmitted</th><th>deadline misses</th>
<th>latency p50 (ms)</th><th>latency p99 (ms)</th><th>staleness p99 (ms)</th>
<th>last sample (s ago)</th><th>driver errors</th><th>late reads</th><th>last driver error</th>
</tr></thead>
<tbody></tbody></table></div>
<small>Counters are a robot's current incarnation's (a restart starts them from zero; earlier
incarnations are summed apart: "earlier incarnations" is how many, and what the CEDDP received
from them); rates are over the last 2 s, percentiles of the last metrics interval. "—": not
measured (yet). Link quality: retransmitted and gapped are the robot's reliable channel's own
counters (gapped: NACKed after its history let the sample go). Driver errors: reads that gave no
reading (the driver raised, or its value was refused, NaN included); a silent sensor gave none
for the robot's whole last report interval. A robot id two processes run with is flagged red:
the newer one's samples are dropped.</small>
</main>
<script>
"use strict";
let polls = 0;
const dash = "\\u2014";
function num(v, digits) {
  if (v === null || v === undefined) return dash;
  return typeof v === "number" ? v.toFixed(digits === undefined ? 0 : digits) : String(v);
}
function pct(v) { return v === null || v === undefined ? dash : (100 * v).toFixed(2) + " %"; }
function cell(text, cls) {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  return td;
}
function row(cells, id) {
  const tr = document.createElement("tr");
  if (id) tr.id = id;
  for (const c of cells) tr.appendChild(typeof c === "string" ? cell(c) : c);
  return tr;
}
function card(label, value) {
  const d = document.createElement("div");
  d.className = "card";
  d.textContent = label;
  const b = document.createElement("b");
  b.textContent = value;
  d.appendChild(b);
  return d;
}
function links(s) {
  const host = location.hostname;
  const out = ['<a href="/api/status">/api/status</a>', '<a href="/metrics">/metrics</a>'];
  if (s.rerun_web_port) {
    const grpc = encodeURIComponent("rerun+http://" + host + ":" + s.grpc_port + "/proxy");
    out.push('<a id="rerun-link" href="http://' + host + ":" + s.rerun_web_port + "/?url=" +
             grpc + '">Rerun web viewer (live recording)</a>');
  }
  if (s.foxglove_port) out.push("Foxglove: ws://" + host + ":" + s.foxglove_port);
  return out.join(" · ");
}
function render(s) {
  document.getElementById("fleet").textContent = s.fleet +
    (s.partition !== "*" ? " (partition " + s.partition + ")" : "");
  document.getElementById("updated").textContent = new Date(s.stamp_ns / 1e6).toLocaleTimeString();
  document.getElementById("polls").textContent = String(++polls);
  document.getElementById("links").innerHTML = links(s);
  const c = s.ceddp, cards = document.getElementById("cards");
  const alive = s.robots.filter(r => r.alive).length;
  cards.replaceChildren(
    card("robots alive", alive + " / " + s.robots.length),
    card("samples ingested", num(c.processed)),
    card("CEDDP CPU %", num(c.cpu_percent, 1)),
    card("ingest load", pct(c.ingest_load)),
    card("ingest backlog (ms)", num(c.ingest_backlog_ms, 1)),
    card("budget (samples/s)", num(c.budget_hz)),
    card("channel NACKs", c.channel ? num(c.channel.nacks) : dash),
    card("channel lost", c.channel ? num(c.channel.lost) : dash),
    card("uptime (s)", num(s.uptime_s)));
  const robots = document.querySelector("#robots tbody");
  const topics = document.querySelector("#topics tbody");
  robots.replaceChildren(...s.robots.map(r => {
    const tr = row([r.robot, cell(r.alive ? "up" : "away", r.alive ? "up" : "down"),
      num(r.qos_epoch), num(r.qos_rate_hz, 1), num(r.qos_depth), num(r.rate_hz, 1),
      num(r.received), num(r.lost), pct(r.loss_ratio), num(r.sent), num(r.retransmitted),
      num(r.gapped), num(r.deadline_missed), num(r.latency_ms_p99, 1),
      num(r.staleness_ms_p99, 1), num(r.last_sample_age_s, 1), num(r.clock_offset_ms, 2),
      num(r.clock_delay_ms, 2), num(r.cpu_percent, 1), num(r.driver_errors),
      cell(r.silent_sensors.join(", ") || dash, "l"), cell(r.incarnation || dash, "l"),
      r.previous.incarnations ? r.previous.incarnations + " (received " +
        num(r.previous.received) + ")" : dash], "robot-" + r.robot);
    tr.dataset.received = String(r.received);
    tr.dataset.incarnation = r.incarnation || "";
    const bad = r.incompatible_qos.slice();
    if (r.duplicates.length) bad.push("robot id used by another process too (incarnation " +
      r.duplicates.join(", ") + "): its samples are dropped (" + r.duplicate_dropped + ")");
    if (bad.length) {
      tr.className = "bad";
      tr.title = bad.join("\\n");
    } else if (r.silent_sensors.length || r.driver_errors > 0) {
      tr.className = "warn";
      tr.title = "driver errors: see the topics";
    } else if (r.loss_ratio > 0.01 || r.deadline_missed > 0) tr.className = "warn";
    return tr;
  }));
  topics.replaceChildren(...s.robots.flatMap(r => r.topics.map(t => {
    const tr = row([
      r.robot + " / " + t.topic, cell(t.kind || dash, "l"), num(t.rate_hz, 1), num(t.received),
      num(t.lost), num(t.retransmitted), num(t.deadline_missed), num(t.latency_ms_p50, 1),
      num(t.latency_ms_p99, 1), num(t.staleness_ms_p99, 1), num(t.last_sample_age_s, 1),
      num(t.driver_errors), num(t.late_reads), cell(t.last_driver_error || dash, "l")],
      "topic-" + r.robot + "-" + t.topic);
    if (t.silent) tr.className = "bad";
    else if (t.driver_errors > 0 || t.late_reads > 0) tr.className = "warn";
    return tr;
  })));
}
async function poll() {
  try {
    const response = await fetch("/api/status", {cache: "no-store"});
    if (!response.ok) throw new Error("HTTP " + response.status);
    render(await response.json());
    document.getElementById("error").textContent = "";
  } catch (e) {
    document.getElementById("error").textContent = "cannot reach the CEDDP: " + e.message;
  }
}
poll();
setInterval(poll, 1000);
</script></body></html>
"""
