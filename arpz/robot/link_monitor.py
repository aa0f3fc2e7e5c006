"""The robot's own watch on its link to the CEDDP: drops, reopens, reconnections (issue 39).

Zenoh notices a dead link only when the router's lease (10 s) runs out, and over TLS not even
then: the link's writer is stuck on a socket that can send nothing (after a roam, until the
kernel gives up, 15 minutes). So the robot watches for itself what it hears from the CEDDP:

- **silence**: nothing heard (an acknowledgement of its reliable writers, a clock reply, a
  command, the CEDDP's presence) for ``[link] silence_s`` while something it sent waits for an
  answer (an unacknowledged sample, an unanswered clock request);
- **presence**: the CEDDP's liveliness token ``arpz/{fleet}/ceddp/presence`` vanished (Zenoh
  closed the session, or the CEDDP stopped);
- **address**: the robot's source address towards the CEDDP changed, or it has no route any
  more (a roam to another access point's subnet, an interface gone). Not watched when every
  endpoint is ``quic/``: QUIC carries its connection over to the new address by itself
  (measured, docs/deploy.md).

A loss is logged once ("link to the CEDDP lost: why"). After an address change the session is
reopened at once; after silence or a vanished presence Zenoh gets ``zenoh_grace_s`` to come back
by itself first. Reopen attempts (``Reopenable.reopen``: a new session, everything declared
again, the same writers and readers) are spaced ``reopen_backoff_s`` doubling to
``reopen_backoff_max_s``, never a busy loop, each one bounded by Zenoh's ``open_timeout``. The
link is back when something is heard again with the CEDDP present ("link to the CEDDP back:
reconnected after X.X s"). Every drop is kept with its cause and durations for the robot's
summary (``--summary-json``).

``LinkMonitor`` is the decision, pure (times are given to it: tests drive it with a fake
clock); ``LinkWatch`` runs it on a thread of its own, reading the signals and reopening.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import msgspec

from arpz.core.config import LinkConfig
from arpz.core.transport import Reopenable, TransportError

log = logging.getLogger("arpz.robot.link")


@dataclass(frozen=True)
class Signals:
    """One reading of what the robot heard from the CEDDP and asked of it."""

    #: grows with every sign of the CEDDP: anything the session delivered (ACKNACKs and
    #: heartbeats of the reliable channel, clock replies, liveliness changes), commands
    heard: int
    #: grows with everything sent that waits for an answer (a sample a reliable reader has not
    #: acknowledged yet, a clock request)
    asked: int
    #: the CEDDP's presence token alive (None: never seen, not known)
    present: bool | None = None
    #: the robot's source address towards each CEDDP endpoint now, () when there is no route;
    #: None when the address is not watched
    route: tuple[str, ...] | None = None


class LinkDrop(msgspec.Struct, kw_only=True):
    """One loss of the link and how it ended, for the log and the robot's summary."""

    #: when it was noticed (Unix time, s) and why
    lost_at: float
    reason: str
    #: how long nothing had been heard from the CEDDP when the loss was noticed
    silent_s: float
    #: when the link was back (Unix time, s); None: not (yet)
    back_at: float | None = None
    #: noticed -> back, and last heard -> back (what a user of the link went without)
    duration_s: float | None = None
    outage_s: float | None = None
    #: reopen attempts made, and whether the link came back on a reopened session (False:
    #: Zenoh's own session came back by itself)
    reopen_attempts: int = 0
    reopened: bool = False


class LinkMonitor:
    """Decides when the link is lost, when to reopen the session, and when it is back.

    Call ``observe(now_s, signals)`` regularly; when it returns True, reopen the session and
    report the outcome with ``attempt_done``. ``now_s`` is monotonic; ``wall_s`` (Unix time)
    only stamps the drops."""

    def __init__(
        self,
        config: LinkConfig,
        now_s: float,
        *,
        wall_s: Callable[[], float] = time.time,
    ) -> None:
        self.config = config
        self._wall_s = wall_s
        self.lost = False
        self._heard: int | None = None
        self._asked: int | None = None
        self._last_heard_s = now_s
        #: since when something asked has been waiting, with nothing heard since
        self._waiting_since: float | None = None
        self._present: bool | None = None
        #: the route the link was (re)established on: a change from it is a roam
        self._route: tuple[str, ...] | None = None
        self._lost_at_s = 0.0
        self._heard_at_loss = 0
        self._next_attempt_s = math.inf
        self._backoff_s = config.reopen_backoff_s
        self._attempts = 0
        self._attempt_started_s = 0.0
        self._reopened = False
        self._lock = threading.Lock()
        self._drops: list[LinkDrop] = []
        #: every reopen attempt, and those that opened a session
        self.reopen_attempts = 0
        self.reopens = 0

    # -- the decision -----------------------------------------------------------------------

    def observe(self, now_s: float, signals: Signals) -> bool:
        """Take one reading; True: reopen the session now (then call ``attempt_done``)."""
        heard_moved = self._heard is not None and signals.heard != self._heard
        asked_moved = self._asked is not None and signals.asked != self._asked
        if self._heard is None or heard_moved:
            self._last_heard_s = now_s
            # what was asked in the same interval may be after the answer: it waits from now
            self._waiting_since = now_s if asked_moved else None
        elif asked_moved and self._waiting_since is None:
            self._waiting_since = now_s
        self._heard, self._asked = signals.heard, signals.asked
        was_present, self._present = (
            self._present,
            (signals.present if signals.present is not None else self._present),
        )
        if self._route is None:
            self._route = signals.route
        if not self.lost:
            self._check_loss(now_s, signals, was_present)
        elif self._back(signals):
            self._recover(now_s, signals)
        if self.lost and now_s >= self._next_attempt_s:
            self._next_attempt_s = math.inf  # until ``attempt_done`` says how it went
            self._attempt_started_s = now_s
            return True
        return False

    def _check_loss(self, now_s: float, signals: Signals, was_present: bool | None) -> None:
        cfg = self.config
        route = signals.route
        if route is not None and self._route is not None and route != self._route:
            if route:
                was = ", ".join(self._route) or "none"
                why = f"this robot's address towards the CEDDP changed ({was} -> "
                self._lose(now_s, why + f"{', '.join(route)})", grace_s=0.0)
            else:
                self._lose(now_s, "no route to the CEDDP", grace_s=0.0)
        elif signals.present is False and was_present:
            self._lose(now_s, "the CEDDP's presence vanished", grace_s=cfg.zenoh_grace_s)
        elif self._waiting_since is not None and now_s - self._waiting_since >= cfg.silence_s:
            self._lose(
                now_s,
                f"nothing heard from the CEDDP for {now_s - self._last_heard_s:.1f} s while "
                "data waited for it",
                grace_s=cfg.zenoh_grace_s,
            )

    def _back(self, signals: Signals) -> bool:
        """Heard from the CEDDP since the loss, with its presence there and a route to it."""
        return (
            signals.heard != self._heard_at_loss
            and self._present is not False
            and signals.route != ()
        )

    def _lose(self, now_s: float, reason: str, *, grace_s: float) -> None:
        silent_s = now_s - self._last_heard_s
        self.lost = True
        self._lost_at_s = now_s
        self._heard_at_loss = self._heard or 0
        self._next_attempt_s = now_s + grace_s
        self._backoff_s = self.config.reopen_backoff_s
        self._attempts = 0
        self._reopened = False
        with self._lock:
            self._drops.append(
                LinkDrop(lost_at=self._wall_s(), reason=reason, silent_s=round(silent_s, 3))
            )
        log.warning("link to the CEDDP lost: %s (last heard from it %.1f s ago)", reason, silent_s)

    def _recover(self, now_s: float, signals: Signals) -> None:
        duration_s = now_s - self._lost_at_s
        with self._lock:
            drop = self._drops[-1]
            outage_s = duration_s + drop.silent_s
            drop.back_at = self._wall_s()
            drop.duration_s = round(duration_s, 3)
            drop.outage_s = round(outage_s, 3)
            drop.reopen_attempts = self._attempts
            drop.reopened = self._reopened
        self.lost = False
        self._next_attempt_s = math.inf
        self._route = signals.route  # the address the link is back on
        self._waiting_since = None
        how = (
            f"session reopened, attempt {self._attempts}"
            if self._reopened
            else "Zenoh's session came back by itself"
        )
        log.info(
            "link to the CEDDP back: reconnected after %.1f s (%s; %.1f s without the CEDDP in "
            "all)",
            duration_s,
            how,
            outage_s,
        )

    def attempt_done(self, now_s: float, opened: bool, error: str = "") -> None:
        """How the reopen ``observe`` asked for went. Opened: the new session gets
        ``silence_s`` to bring something from the CEDDP before the next attempt. Failed after
        waiting (a dead link: the attempt spent Zenoh's ``open_timeout``, 1.5 s, 0.5 s on UDP,
        at least ``reopen_backoff_s`` in all): the next one at once, so that an attempt starts
        within that timeout (and a reading) of the link coming back. Failed at once (refused,
        no route): the next one the backoff after this one started, the backoff doubling up to
        its maximum (0.25, 0.5, then 1 s): never a busy loop."""
        self._attempts += 1
        self.reopen_attempts += 1
        if opened:
            self.reopens += 1
            self._reopened = True
            self._backoff_s = self.config.reopen_backoff_s
            if self.lost:
                self._next_attempt_s = now_s + self.config.silence_s
            log.debug("session reopened (attempt %d)", self._attempts)
            return
        waited = now_s - self._attempt_started_s >= self.config.reopen_backoff_s
        if self.lost:
            self._next_attempt_s = now_s if waited else self._attempt_started_s + self._backoff_s
        if not waited:
            self._backoff_s = min(self._backoff_s * 2, self.config.reopen_backoff_max_s)
        log.debug("reopen attempt %d failed: %s", self._attempts, error)

    # -- what happened --------------------------------------------------------------------

    def drops(self) -> list[LinkDrop]:
        """Every drop so far (copies: safe to read from another thread)."""
        with self._lock:
            return [msgspec.structs.replace(d) for d in self._drops]

    def summary(self) -> dict[str, object]:
        """The ``link`` section of the robot's summary."""
        drops = self.drops()
        return {
            "drops": len(drops),
            "reconnections": sum(d.back_at is not None for d in drops),
            "lost_now": self.lost,
            "reopen_attempts": self.reopen_attempts,
            "reopens": self.reopens,
            "down_s": round(sum(d.duration_s or 0.0 for d in drops), 3),
            "events": msgspec.to_builtins(drops),
        }


class Waiting:
    """Counts what this robot's reliable writers wrote that waits for an acknowledgement: the
    ``asked`` of ``Signals``. A writer asks only while a reader is matched and its last sample
    is not acknowledged (``acknowledged_through`` follows the last seq with no reader matched,
    and a best-effort reader never acknowledges). What was acknowledged is no sign of the CEDDP:
    a KEEP_LAST writer lets go of what it overwrote, acknowledged or not."""

    def __init__(self) -> None:
        self._sent: dict[str, int] = {}
        self.asked = 0

    def update(self, readings: Sequence[tuple[str, bool, int, int]]) -> int:
        """``(key, matched, acknowledged_through, sent)`` of each writer; ``asked`` so far."""
        for key, matched, acked, sent in readings:
            before = self._sent.get(key, 0)
            self._sent[key] = sent
            if matched and acked < sent and sent > before:
                self.asked += sent - before
        return self.asked


def route_sources(targets: Sequence[tuple[str, int]]) -> tuple[str, ...]:
    """The source address the kernel would use towards each target now (a connected UDP
    socket: a route lookup, nothing is sent); targets without a route are left out."""
    sources: list[str] = []
    for host, port in targets:
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        try:
            with socket.socket(family, socket.SOCK_DGRAM) as probe:
                probe.connect((host, port))
                sources.append(str(probe.getsockname()[0]))
        except OSError:
            continue  # no route (network unreachable, no address)
    return tuple(sources)


class LinkWatch:
    """``LinkMonitor`` on a thread of its own (``arpz-link``): reads ``signals()`` every
    ``check_period_s`` and reopens ``transport`` when the monitor says so. ``on_change`` is
    called (on that thread) after each drop and each reconnection."""

    def __init__(
        self,
        config: LinkConfig,
        transport: Reopenable,
        signals: Callable[[], Signals],
        *,
        on_change: Callable[[], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self._transport = transport
        self._signals = signals
        #: called on this watch's thread after each drop and each reconnection
        self.on_change = on_change
        self._clock = clock
        self.monitor = LinkMonitor(config, clock())
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="arpz-link", daemon=True)

    def start(self) -> None:
        """Take the first reading now (its address is the one the session was opened on),
        then watch on the thread."""
        self.monitor.observe(self._clock(), self._signals())
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop watching (a reopen under way finishes first, bounded by Zenoh's open
        timeout)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    def _run(self) -> None:
        monitor = self.monitor
        while not self._stop.wait(self.config.check_period_s):
            try:
                signals = self._signals()
            except Exception:  # a reading must never end the watch
                log.exception("reading the link's signals failed")
                continue
            was_lost = monitor.lost
            reopen = monitor.observe(self._clock(), signals)
            if monitor.lost != was_lost:
                self._changed()
            if reopen and not self._stop.is_set():
                log.debug("reopening the session (attempt %d)", monitor.reopen_attempts + 1)
                try:
                    self._transport.reopen()
                except TransportError as exc:
                    monitor.attempt_done(self._clock(), False, str(exc))
                else:
                    monitor.attempt_done(self._clock(), True)

    def _changed(self) -> None:
        if self.on_change is None:
            return
        try:
            self.on_change()
        except Exception:
            log.exception("link change callback failed")
