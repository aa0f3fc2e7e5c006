"""The reader side of the reliable protocol as a pure state machine: values in, actions out.

One ``ReaderMachine`` serves a key expression that may contain wildcards, so it keeps one
``_WriterProxy`` per matched writer (per writer incarnation). For each it delivers in seq order,
NACKs gaps, and declares a missing sample lost when the writer says so (GAP, or a heartbeat whose
first held seq is past it) or when it has held later samples back for ``reorder_timeout_s``.
Every seq of the match therefore ends up exactly once in ``delivered``, ``lost`` or
``lifespan_expired``.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence

import msgspec

from arpz.core.protocol import wire
from arpz.core.protocol._common import AWAY_RETENTION_S, BadInput, parse_token
from arpz.core.protocol.actions import Action, Deliver, DeliverRun, Notify, Send, TokenChange
from arpz.core.protocol.events import (
    DataInfo,
    DeadlineMissedStatus,
    IncompatibleQosStatus,
    LivelinessChangedStatus,
    MatchedStatus,
    MessageLostStatus,
    UnchangedStatus,
)
from arpz.core.protocol.fragments import SampleParts
from arpz.core.protocol.qos import (
    HistoryPolicy,
    QosPolicyKind,
    QosProfile,
    encode_match_qos,
    incompatible_policy,
    rounded,
)
from arpz.core.protocol.timers import Clock, DeadlineTimer, LeaseTimer

#: keys whose plain samples are counted one by one; beyond, they share OTHER_PLAIN_KEYS
MAX_PLAIN_KEYS = 1024
OTHER_PLAIN_KEYS = "(other keys)"
#: prefix of ``IncompatibleQosStatus.peer`` when the peer is a plain publisher on that key
PLAIN_PEER = "plain:"
#: writers matched on one concrete key (a restarted process is one more until the old token
#: goes): beyond, tokens are refused and counted, so invented guids cannot grow the reader
MAX_WRITERS_PER_KEY = 16
#: writers one reader matches in all (a CEDDP passes max_robots x max_topics_per_robot)
DEFAULT_MAX_WRITERS = 65_536
#: NACKs per writer whose send times are kept for their resends to time (the oldest go first)
MAX_NACKS_TIMED = 64
#: the NACK hold is this many times longer while samples are queued before the machine: a
#: restarted CEDDP catching up takes its answers in too slowly for the plain hold (more resends
#: than history in ``python -m pytest tests/integration/test_faults.py -s -k high_rate``), but
#: under a lasting backlog a lost resend must still be asked again
QUEUED_HOLD_FACTOR = 4
#: doublings of the NACK hold at most (x2): more stretches recovery at 50 % loss past the 3 s
#: the property tests of tests/unit/reliability/test_machines.py allow (x8 failed them)
MAX_NACK_BACKOFF = 1
#: the largest sample a reader reassembles from fragments by default; a larger one is refused at
#: its first fragment and counted lost (``ReaderStats.samples_too_large``)
DEFAULT_MAX_SAMPLE_BYTES = 16 * 2**20
#: the most bytes a reader reserves for samples being reassembled, over all its writers; a
#: fragment that would start one more beyond it is refused (counted), and its sample is asked
#: for again once there is room, or given up as any missing sample is
DEFAULT_MAX_ASSEMBLY_BYTES = 64 * 2**20


class ReaderStats(msgspec.Struct, frozen=True):
    delivered: int
    lost: int
    lifespan_expired: int
    duplicates: int
    #: BEST_EFFORT: arrived after a later sample had been delivered (already counted lost)
    late: int
    #: delivered samples that arrived by retransmission
    retransmitted: int
    #: ACKNACKs that asked for at least one sample
    nacks: int
    acks: int
    gaps: int
    unchanged: int
    deadline_missed: int
    matched: int
    incompatible: int
    #: samples from before the match (a TRANSIENT_LOCAL history window or a race with SYNC)
    before_match: int
    bad_input: int
    #: refused by the full worker queue (reliable readers get them again by NACK)
    queue_dropped: int = 0
    #: exceptions raised by user callbacks (logged, the channel goes on)
    callback_errors: int = 0
    #: plain Zenoh samples (no channel header) refused: an INCOMPATIBLE_QOS publisher
    plain_refused: int = 0
    #: messages (part of bad_input) refused for carrying the guid of a writer of another key
    impersonations: int = 0
    #: samples and heartbeats (part of bad_input) refused for a seq beyond the writer's reach
    implausible: int = 0
    #: writer tokens refused beyond MAX_WRITERS_PER_KEY or the reader's max_writers
    writers_refused: int = 0
    #: matches that went on after the writer's token came back (its session was lost and
    #: reopened: a dead zone, a roam), instead of starting again as a new writer
    resumed: int = 0
    #: writers away now: token gone, state kept for AWAY_RETENTION_S in case they come back
    away: int = 0
    #: fragments of samples larger than the writer's fragment size (DATA_FRAG): each sample is
    #: counted once above (``delivered`` once whole, or ``lost``), these count its pieces
    fragments_received: int = 0
    #: a fragment received already, or of a sample already delivered or given up
    fragments_duplicate: int = 0
    #: refused: beyond ``max_assembly_bytes``, of a sample too large, or malformed (bad_input)
    fragments_refused: int = 0
    #: samples announcing more than ``max_sample_bytes``: counted lost, never reassembled
    samples_too_large: int = 0
    #: fragments asked for by ACKNACK_FRAG (only the missing pieces of a partly received sample)
    fragments_nacked: int = 0
    #: samples being reassembled now, and the bytes reserved for them
    in_assembly: int = 0
    assembly_bytes: int = 0


class _WriterProxy:
    """The reader's view of one matched writer."""

    __slots__ = (
        "an_count",
        "an_due_s",
        "an_key",
        "announced",
        "buffer",
        "confirmed_high",
        "deadline",
        "delivered",
        "detect",
        "expected",
        "expired",
        "gaps",
        "gone_below",
        "guid",
        "held_from",
        "hex",
        "highest",
        "lease",
        "leaving_s",
        "lost",
        "manual",
        "nack_high",
        "nack_high_s",
        "nack_sent",
        "partials",
        "srtt_s",
        "start",
        "synced",
        "topic",
        "unanswered",
    )

    def __init__(
        self,
        guid: bytes,
        hex_: str,
        topic: str,
        an_key: str,
        manual: bool,
        deadline_s: float,
        lease_s: float,
        now: float,
    ) -> None:
        self.guid, self.hex, self.topic, self.an_key, self.manual = (
            guid,
            hex_,
            topic,
            an_key,
            manual,
        )
        self.synced = False
        #: first seq of the match (known once synced)
        self.start = 0
        #: next seq to deliver; all below are delivered or declared lost
        self.expected = 1
        #: highest seq known to exist (from data or heartbeats)
        self.highest = 0
        #: highest seq the writer proved it sent: received as data, or answered by a GAP. A
        #: heartbeat alone can be forged (its key is public), so only this bounds how far time
        #: or a writer's departure may declare samples lost
        self.confirmed_high = 0
        #: highest seq a heartbeat announced: the writer had put all of its fragments
        self.announced = 0
        #: out-of-order samples: seq -> (payload, stamp_ns, flags)
        self.buffer: dict[int, tuple[bytes, int, int]] = {}
        #: (seq, when): a heartbeat said nothing below seq is held any more; settle at ``when``
        self.gone_below: tuple[int, float] | None = None
        #: the oldest seq the writer's last heartbeat says it still holds (0: no heartbeat yet)
        self.held_from = 0
        #: GAP ranges not yet reached, sorted
        self.gaps: list[tuple[int, int]] = []
        #: (last seq of a missing run, time it was first seen missing), increasing in both
        self.detect: list[tuple[int, float]] = []
        self.an_due_s = math.inf
        self.an_count = 0
        #: the writer's token vanished; the match ends (and losses are counted) at this time
        self.leaving_s: float | None = None
        #: when each recent NACK left, by its ACKNACK count (a resend echoes the count it
        #: answers), and the smoothed NACK -> resend round trip they measure
        self.nack_sent: dict[int, float] = {}
        self.srtt_s = 0.0
        #: the highest seq the last full NACK asked for, and when: within the NACK hold of it
        #: those seqs are not asked for again (their resends are still on their way)
        self.nack_high = 0
        self.nack_high_s = -math.inf
        #: full NACKs in a row without a resend answering any: each doubles the hold
        self.unanswered = 0
        self.expired = 0
        self.delivered = 0
        self.lost = 0
        #: samples received in part (DATA_FRAG), by seq: all at or above ``expected``
        self.partials: dict[int, SampleParts] = {}
        self.deadline = DeadlineTimer(deadline_s, now)
        self.lease = LeaseTimer(lease_s, now)


def _pending(p: _WriterProxy) -> bool:
    """Writer ``p`` needs the fine timer: an ACKNACK is due, samples wait in order, a loss is
    to be settled, its match is ending, or a seq it sent is still missing."""
    return (
        p.an_due_s != math.inf
        or bool(p.buffer)
        or p.gone_below is not None
        or p.leaving_s is not None
        or p.highest >= p.expected
    )


class ReaderMachine:
    def __init__(
        self,
        key_expr: str,
        qos: QosProfile,
        guid: bytes,
        clock: Clock,
        *,
        max_writers: int = DEFAULT_MAX_WRITERS,
        away_retention_s: float = AWAY_RETENTION_S,
        max_sample_bytes: int = DEFAULT_MAX_SAMPLE_BYTES,
        max_assembly_bytes: int = DEFAULT_MAX_ASSEMBLY_BYTES,
    ) -> None:
        self.key_expr = wire.check_key_expr(key_expr)
        if max_sample_bytes < 1 or max_assembly_bytes < 1:
            raise ValueError("max_sample_bytes and max_assembly_bytes must be >= 1")
        self.max_sample_bytes = max_sample_bytes
        self.max_assembly_bytes = max_assembly_bytes
        #: bytes reserved by every writer's samples in assembly (``_WriterProxy.partials``)
        self._assembly_bytes = 0
        self.fragments_received = self.fragments_duplicate = self.fragments_refused = 0
        self.samples_too_large = self.fragments_nacked = 0
        self.max_writers = max_writers
        self.away_retention_s = away_retention_s
        #: writers whose token vanished, by (key, guid), with when their state expires (in that
        #: order: insertion order is expiry order). A writer whose session was lost comes back
        #: with the same guid and seqs; its match resumes where it stopped instead of starting
        #: over, which delivered a TRANSIENT_LOCAL history twice and lost count of the gap
        #: (issue 39). Bounded by max_writers.
        self._away: dict[tuple[str, bytes], tuple[_WriterProxy, float]] = {}
        self.resumed = 0
        #: writer tokens refused for exceeding MAX_WRITERS_PER_KEY or max_writers
        self.writers_refused = 0
        self.qos = qos
        self.guid = guid
        self.hex = guid.hex()
        self.clock = clock
        self.bad = BadInput(f"reader {key_expr} {self.hex}")
        self._requested = rounded(qos)
        self._qos_chunk = encode_match_qos(qos)
        self._reliable = qos.reliable
        #: KEEP_ALL: nothing the writer still holds is ever given up by time (see _give_up)
        self._keep_all = qos.history is HistoryPolicy.KEEP_ALL
        self._cap = qos.capacity
        #: BEST_EFFORT: how far past the data a heartbeat is believed (no NACK can confirm it).
        #: At least one whole message of the largest batch, so that a batch lost at the end of a
        #: stream is counted; at most that, so that a forged heartbeat skips one window at most.
        self._trust_window = max(self._cap, wire.MAX_BATCH)
        self._deep = "**" in key_expr
        self._lifespan_ns = int(qos.lifespan_s * 1e9)
        self._mono = clock.monotonic_s
        self._unpack = wire.DATA.unpack
        #: matched writers by (key, guid): a writer's identity is bound to the key it writes, so
        #: a message carrying its guid on any other key is never taken for its own
        self.writers: dict[tuple[str, bytes], _WriterProxy] = {}
        #: every writer proxy that may need the fine timer (see ``busy``): a superset of the busy
        #: ones, kept by each path that can make a proxy busy. ``busy`` runs after every pass of
        #: the delivery thread; looking at every writer there cost a fleet CEDDP (80 writers)
        #: 7 % of its sensor path, growing with the fleet (issue 17)
        self._suspects: set[_WriterProxy] = set()
        #: every writer token seen (compatible or not), for our per-topic tokens
        self._writer_tokens: set[tuple[str, bytes]] = set()
        self._topic_writers: dict[str, int] = {}
        self._incompatible: set[tuple[str, bytes]] = set()
        #: messages refused because they carried the guid of a writer of another key
        self.impersonations = 0
        #: samples, heartbeats and GAPs refused for a seq no writer could have reached yet
        self.implausible = 0
        #: more samples are queued before this machine (its channel says so): a full NACK now
        #: would ask again for what may be among them
        self.queued = False
        #: the channel's FIFO in front of this machine held nothing older than this (monotonic
        #: s; inf: no FIFO, or it is empty now). A heartbeat seen later than it may announce
        #: data that are only queued there, not lost: its NACK waits until the FIFO has drained
        #: past it (``drained``). Without this wait a CEDDP behind on its sensor FIFO NACKed
        #: what it had not read yet: ``python benchmarks/ceddp_ingest.py`` printed 52 000-109 000
        #: duplicates of 200 000 samples batched, 173 000-223 000 unbatched (issue 17).
        self.drained_s = math.inf
        #: the channel's delivery thread found data waiting in its FIFO (more than one message
        #: at its last pull): it is behind, and only then does a NACK wait for the drain. A
        #: reader keeping up finds one message a pull; there the wait only delayed the recovery
        #: of real losses (``python benchmarks/reliability_lossy.py``, 1 kHz at 30 % loss: always
        #: waiting, the p99 was 1.2x that with this condition and 1.4x that of no wait at all;
        #: benchmarks/RESULTS.md)
        self.fifo_behind = False
        #: writers whose NACK waits only for the FIFO to drain, with the time it must pass
        self._drain_waiters: dict[_WriterProxy, float] = {}
        #: how often ``tick`` polls every writer's deadline and lease (as often as the
        #: channel's idle timer ticks, arpz/channel/_channel.py), and when next
        self._full_period_s = min(
            [0.05] + [v / 10 for v in (qos.deadline_s, qos.lease_duration_s) if v > 0]
        )
        self._next_full_s = -math.inf
        self.delivered = self.lost = self.lifespan_expired = self.duplicates = self.late = 0
        self.retransmitted = self.nacks = self.acks = self.gaps = self.unchanged = 0
        self.deadline_missed = self.incompatible = self.before_match = 0
        self.matched_total = 0
        self.alive_count = self.not_alive_count = 0
        #: plain (header-less) samples refused, per key: their publisher has no channel
        self.plain_samples: dict[str, int] = {}

    # ------------------------------------------------------------------ routing
    def subscriptions(self) -> list[tuple[str, str]]:
        e = self.key_expr
        return [
            (e, "on_data"),
            (wire.heartbeat_key(e, "*"), "on_heartbeat"),
            (wire.directed_key(e, self.hex), "on_directed"),
        ]

    def watch_expr(self) -> str:
        return wire.writer_token(self.key_expr, "*", "*")

    def retune(self, *, depth: int) -> None:
        """Follow a QoS assignment's KEEP_LAST depth (the writers were retuned to it): the reorder
        window and the trust window of heartbeats track the writers' history. A window smaller
        than what is buffered now shrinks as samples are delivered."""
        qos = msgspec.structs.replace(self.qos, depth=depth)
        QosProfile.__post_init__(qos)  # the same validation as a profile built from TOML
        self.qos = qos
        self._cap = qos.capacity
        self._trust_window = max(self._cap, wire.MAX_BATCH)

    # ------------------------------------------------------------------ matching
    def on_writer_token(self, key: str, alive: bool) -> list[Action]:
        parsed = parse_token(key, "w", None)
        if parsed is None:
            self.bad("malformed writer token", key)
            return []
        topic, guid, hex_, mq = parsed
        now = self.clock.monotonic_s()
        actions: list[Action] = []
        ident = (topic, guid)
        if not alive:
            if ident in self._writer_tokens:
                self._writer_tokens.discard(ident)
                self._topic_writers[topic] -= 1
                if self._topic_writers[topic] == 0:
                    del self._topic_writers[topic]
                    actions.append(TokenChange(self._token(topic), False))
            self._incompatible.discard(ident)
            p = self.writers.get(ident)
            if p is not None and p.leaving_s is None:
                # The token's removal can overtake the writer's last samples: let them land.
                p.leaving_s = now + self.qos.nack_period_s
                self._suspects.add(p)
            return actions
        if ident in self._writer_tokens:
            return []
        if (
            self._topic_writers.get(topic, 0) >= MAX_WRITERS_PER_KEY
            or len(self._writer_tokens) >= self.max_writers
        ):
            self.writers_refused += 1
            self.bad("writer token beyond the writer bounds", key)
            return []
        self._writer_tokens.add(ident)
        self._topic_writers[topic] = self._topic_writers.get(topic, 0) + 1
        if self._topic_writers[topic] == 1:
            # The writer learns about us (and checks compatibility itself) from this token.
            actions.append(TokenChange(self._token(topic), True))
        if ident in self.writers:  # the token flapped (a reconnection): the match goes on
            self.writers[ident].leaving_s = None
            return actions
        policy = incompatible_policy(mq.as_profile(), self._requested)
        away = self._away.pop(ident, None)
        if away is not None:
            if policy is None:
                self._resume(away[0], now, actions)
                return actions
            self._forget(away[0], now, actions)
        if policy is not None:
            self._incompatible.add(ident)
            self.incompatible += 1
            actions.append(
                Notify(
                    "incompatible_qos", IncompatibleQosStatus(self.incompatible, 1, policy, hex_)
                )
            )
            return actions
        p = _WriterProxy(
            guid,
            hex_,
            topic,
            wire.acknack_key(topic, hex_, self.hex),
            mq.manual,
            self.qos.deadline_s,
            mq.lease_us / 1e6,
            now,
        )
        self.writers[ident] = p
        self.matched_total += 1
        self.alive_count += 1
        actions.append(self._matched(1, hex_))
        actions.append(self._liveliness(1, 0, hex_))
        return actions

    def _token(self, topic: str) -> str:
        return wire.reader_token(topic, self.hex, self._qos_chunk)

    def _unmatch(self, p: _WriterProxy, now: float, actions: list[Action]) -> None:
        """The writer's token is gone: the match ends. Its state is kept (``_away``) while the
        writer may come back with the same guid; what it sent but we miss is counted lost only
        when it does not (``_forget``)."""
        del self.writers[(p.topic, p.guid)]
        self._suspects.discard(p)
        self._drain_waiters.pop(p, None)
        if p.partials:  # what was in assembly is asked for again if the match resumes
            self._drop_samples_below(p, wire.MAX_SEQ + 1)
        if p.lease.alive:
            self.alive_count -= 1
            actions.append(self._liveliness(-1, 0, p.hex))
        else:
            self.not_alive_count -= 1
            actions.append(self._liveliness(0, -1, p.hex))
        actions.append(self._matched(-1, p.hex))
        if not p.synced:
            return  # nothing of the match is known: nothing to resume or to count
        self._away[(p.topic, p.guid)] = (p, now + self.away_retention_s)
        while len(self._away) > self.max_writers:
            oldest = next(iter(self._away))
            self._forget(self._away.pop(oldest)[0], now, actions)

    def _resume(self, p: _WriterProxy, now: float, actions: list[Action]) -> None:
        """The writer of an away match is back (same key and guid): the match goes on from the
        seq it stopped at. The writer's heartbeats tell what it wrote meanwhile; what it still
        holds is NACKed and resent, the rest is GAPed and counted lost."""
        # The lease and the deadline go on from the writer's last sample: the deadline periods
        # of the gap are missed ones, and the plausible seq range grows with the silence
        # (``_seq_limit``), as the writer went on writing.
        p.leaving_s = None
        p.nack_high, p.nack_high_s, p.unanswered = 0, -math.inf, 0
        p.nack_sent.clear()
        p.an_due_s = now  # an ACKNACK at once: the writer learns where we stand
        self.writers[(p.topic, p.guid)] = p
        self._suspects.add(p)
        self.resumed += 1
        self.matched_total += 1
        actions.append(self._matched(1, p.hex))
        if p.lease.alive:
            self.alive_count += 1
            actions.append(self._liveliness(1, 0, p.hex))
        else:
            self.not_alive_count += 1
            actions.append(self._liveliness(0, 1, p.hex))

    def _forget(self, p: _WriterProxy, now: float, actions: list[Action]) -> None:
        """An away writer did not come back in time (or came back incompatible): what it had
        sent but we still miss can never come."""
        end = min(p.highest, p.confirmed_high) + 1
        if end > p.expected:
            self._skip_to(p, end, actions)
        self._suspects.discard(p)
        self._drain_waiters.pop(p, None)

    def _expire_away(self, now: float, actions: list[Action]) -> None:
        away = self._away
        while away:
            ident = next(iter(away))
            p, until = away[ident]
            if until > now:
                return
            del away[ident]
            self._forget(p, now, actions)

    def _matched(self, change: int, peer: str) -> Notify:
        return Notify(
            "matched",
            MatchedStatus(self.matched_total, max(change, 0), len(self.writers), change, peer),
        )

    def _liveliness(self, alive_change: int, not_alive_change: int, peer: str) -> Notify:
        return Notify(
            "liveliness",
            LivelinessChangedStatus(
                self.alive_count, self.not_alive_count, alive_change, not_alive_change, peer
            ),
        )

    def _alive(self, p: _WriterProxy, now: float, actions: list[Action]) -> None:
        if p.lease.assert_alive(now):
            self.alive_count += 1
            self.not_alive_count -= 1
            actions.append(self._liveliness(1, -1, p.hex))

    # ------------------------------------------------------------------ data
    def on_data(self, key: str, payload: bytes, attachment: bytes | None) -> list[Action]:
        if self._deep and f"/{wire.REL}/" in key:
            return []  # control traffic seen through a ``**`` subscription
        if attachment is None:
            return self._plain(key)
        if len(attachment) != wire.DATA.size:
            return self._on_batch(key, payload, attachment)
        version, flags, writer, seq, stamp = self._unpack(attachment)
        if version != wire.VERSION or seq < 1:
            self.bad("sample with a malformed DATA header", key)
            return []
        p = self.writers.get((key, writer))
        if p is None:
            self._unknown(key, writer, "sample")
            return []
        return self._one(p, flags, seq, stamp, payload)

    def _plain(self, key: str) -> list[Action]:
        """A plain Zenoh put on a key this reader serves: its publisher offers no channel at all
        (``reliability = "none"`` on one side only). As DDS does for a BEST_EFFORT writer and a
        RELIABLE reader, the pair is INCOMPATIBLE_QOS (policy RELIABILITY), reported once per
        key; every such sample is refused and counted per key (bounded), never delivered."""
        self.bad("sample without a DATA header", key, race=True)
        counts = self.plain_samples
        if key not in counts and len(counts) >= MAX_PLAIN_KEYS:
            key = OTHER_PLAIN_KEYS
        seen = counts.get(key, 0)
        counts[key] = seen + 1
        if seen:
            return []
        self.incompatible += 1
        status = IncompatibleQosStatus(
            self.incompatible, 1, QosPolicyKind.RELIABILITY, f"{PLAIN_PEER}{key}"
        )
        return [Notify("incompatible_qos", status)]

    def _on_batch(self, key: str, payload: bytes, attachment: bytes) -> list[Action]:
        """Consecutive samples in one message (the writer's batching): each is handled exactly
        as if it had come alone; only the last carries the batch's ACK_REQUEST."""
        if len(attachment) == wire.DATA_FRAG.size:
            return self._on_fragment(key, payload, attachment, "fragment")
        batch = wire.decode_batch(payload, attachment)
        if batch is None:
            self.bad("sample with a malformed DATA header or batch", key)
            return []
        p = self._known_writer(key, batch.writer, "sample")
        if p is None:
            return []
        flags = batch.flags & ~wire.F_BATCH
        if batch.first == p.expected and self._in_order(p):
            return self._deliver_run(p, flags, batch.first, batch.stamps, batch.payloads)
        plain = flags & ~wire.F_ACK_REQUEST
        last = len(batch.payloads) - 1
        actions: list[Action] = []
        for i, (stamp, data) in enumerate(zip(batch.stamps, batch.payloads, strict=True)):
            header = wire.DataHeader(flags if i == last else plain, p.guid, batch.first + i, stamp)
            actions.extend(self._sample(p, header, data))
        return actions

    def _known_writer(self, topic: str, guid: bytes, what: str) -> _WriterProxy | None:
        """The matched writer ``guid`` of ``topic`` (the key the message came on), or None,
        counted (see ``_unknown``)."""
        p = self.writers.get((topic, guid))
        if p is None:
            self._unknown(topic, guid, what)
        return p

    def _unknown(self, topic: str, guid: bytes, what: str) -> None:
        """Count a message no matched writer of ``topic`` sent: another key's writer's guid is an
        impersonation (refused, never that writer's data or loss); an unknown guid is a race (a
        message may overtake the token that matches its writer) or noise; a known incompatible
        writer's messages are expected and not counted."""
        if (topic, guid) in self._incompatible:
            return
        if any(g == guid for _, g in self.writers):
            self.impersonations += 1
            self.bad(f"{what} with the guid of another key's writer", f"{topic} {guid.hex()}")
            return
        self.bad(f"{what} from an unmatched writer", guid.hex(), race=True)

    # ------------------------------------------------------------------ fragments
    def _on_fragment(
        self, topic: str, payload: bytes, attachment: bytes, what: str
    ) -> list[Action]:
        """A DATA_FRAG (on the topic key) or a resent fragment (on our directed key)."""
        h = wire.decode_frag(attachment)
        if h is None:
            self.fragments_refused += 1
            self.bad(f"malformed {what} header", topic)
            return []
        p = self._known_writer(topic, h.writer, what)
        return self._fragment(p, h, payload) if p is not None else []

    def _fragment(self, p: _WriterProxy, h: wire.FragHeader, data: bytes) -> list[Action]:
        """One fragment of sample ``h.seq``. The sample is a sample like any other for every
        rule of the channel (order, NACKs, losses, accounting) once it is whole; until then it
        is "missing" for them, and the reader asks for the missing fragments only."""
        seq = h.seq
        heard = self._heard(p, seq, h.echo, "fragment")
        if heard is None:
            return []
        now, actions = heard
        self.fragments_received += 1
        if (p.synced and seq < p.expected) or seq in p.buffer:
            self.fragments_duplicate += 1
            return actions
        parts = p.partials.get(seq)
        if parts is None:
            parts = self._start_sample(p, h, now, actions)
            if parts is None:
                return actions
        elif parts.total != h.total or parts.chunk != h.chunk:
            self.fragments_refused += 1
            self.bad("fragment disagreeing with its sample's others", f"{p.topic} {seq}")
            return actions
        high = parts.high
        added = parts.add(h.fragment, data)
        if added is None:
            self.fragments_refused += 1
            self.bad("fragment of the wrong length", f"{p.topic} {seq}")
            return actions
        if not added:
            self.fragments_duplicate += 1
            return actions
        if seq > p.confirmed_high:
            p.confirmed_high = seq
        parts.flags |= h.flags & wire.F_ACK_REQUEST
        if parts.missing:
            if h.fragment > high + 1 and parts.gap_s == math.inf:
                parts.gap_s = now  # fragments between were lost (or overtaken)
                self._fragments_due(p, now)
            if h.fragment == parts.count - 1:
                self._close_sample(p, parts, now)  # the writer sent them all
            return actions
        del p.partials[seq]
        self._assembly_bytes -= parts.total
        flags = (h.flags & wire.F_RETRANSMIT) | parts.flags
        actions.extend(self._one(p, flags, seq, parts.stamp_ns, bytes(parts.buffer)))
        return actions

    def _start_sample(
        self, p: _WriterProxy, h: wire.FragHeader, now: float, actions: list[Action]
    ) -> SampleParts | None:
        """The first fragment seen of sample ``h.seq``: room is reserved for all of it, or the
        fragment is refused (too large a sample is settled as lost at once)."""
        seq = h.seq
        if p.synced and seq > p.highest + 1:
            p.detect.append((seq - 1, now))
            p.an_due_s = min(p.an_due_s, now + self.qos.nack_delay_s)
        if seq > p.highest:
            p.highest = seq
        if p.partials:  # a later sample began: the ones before were sent whole
            self._close_samples_before(p, seq, now)
        if h.total > self.max_sample_bytes:
            self.fragments_refused += 1
            self._refuse_sample(p, seq, actions)
            return None
        if self._assembly_bytes + h.total > self.max_assembly_bytes:
            self.fragments_refused += 1  # asked for again, whole, once there is room
            if p.synced and (not p.detect or p.detect[-1][0] < seq):
                p.detect.append((seq, now))  # missing now: NACKed as any missing seq
                p.an_due_s = min(p.an_due_s, now + self.qos.nack_delay_s)
            return None
        parts = SampleParts(h.total, h.chunk, h.stamp_ns)
        p.partials[seq] = parts
        self._assembly_bytes += h.total
        if seq <= p.announced:  # a heartbeat said so before any of it came (a resent sample)
            self._close_sample(p, parts, now + self.qos.nack_period_s / 4)
        return parts

    def _refuse_sample(self, p: _WriterProxy, seq: int, actions: list[Action]) -> None:
        """A sample larger than ``max_sample_bytes``: settled as lost (once), never NACKed."""
        if not (self._reliable and p.synced):
            return  # a best-effort reader counts it lost when a later sample passes it
        if any(lo <= seq <= hi for lo, hi in p.gaps):
            return
        self.samples_too_large += 1
        if seq > p.confirmed_high:
            p.confirmed_high = seq
        if seq == p.expected:
            self._skip_to(p, seq + 1, actions)
        elif len(p.gaps) < wire.MAX_RANGES:
            bisect.insort(p.gaps, (seq, seq))

    def _close_sample(self, p: _WriterProxy, parts: SampleParts, at: float) -> None:
        """The writer sent every fragment of ``parts`` by ``at``: what is still missing then
        is asked for ``nack_delay_s`` later."""
        if at < parts.closed_s:
            parts.closed_s = at
            self._fragments_due(p, at)

    def _fragments_due(self, p: _WriterProxy, at: float) -> None:
        self._suspects.add(p)
        p.an_due_s = min(p.an_due_s, at + self.qos.nack_delay_s)

    def _close_samples_before(self, p: _WriterProxy, seq: int, at: float) -> None:
        """Data of ``seq`` arrived: the samples before it in assembly were sent whole."""
        for other_seq, other in p.partials.items():
            if other_seq < seq:
                self._close_sample(p, other, at)

    def _drop_samples_below(self, p: _WriterProxy, below: int) -> None:
        """Samples in assembly below ``below`` were given up (or passed): free their room."""
        parts = p.partials
        for seq in [s for s in parts if s < below]:
            self._assembly_bytes -= parts.pop(seq).total

    def _fragment_nacks(
        self, p: _WriterProxy, now: float
    ) -> tuple[list[tuple[int, int, int]], float]:
        """(seq, first index, last index) of the fragments to ask for now, and when the next
        request may be due. A sample's missing fragments are asked for ``nack_delay_s`` after
        they were seen missing (below a later fragment) or after the writer was known to have
        sent them all; not again within the NACK hold, as seqs are not (only new ones)."""
        ripe = now - self.qos.nack_delay_s
        hold = self._nack_hold_s(p) * (QUEUED_HOLD_FACTOR if self.queued else 1)
        asks: list[tuple[int, int, int]] = []
        next_s = math.inf
        for seq in sorted(p.partials):
            parts = p.partials[seq]
            if parts.closed_s <= ripe:
                last, seen_s = parts.count - 1, parts.closed_s
            elif parts.gap_s <= ripe:
                last, seen_s = parts.high - 1, parts.gap_s
            else:
                next_s = min(next_s, min(parts.closed_s, parts.gap_s) + self.qos.nack_delay_s)
                continue
            if self.fifo_behind and seen_s > self.drained_s:
                # its fragments may still be queued before us: asked once the FIFO drained
                self._drain_waiters[p] = max(self._drain_waiters.get(p, seen_s), seen_s)
                next_s = min(next_s, now + self.qos.heartbeat_period_s)
                continue
            first = 0
            if now - parts.asked_s < hold:
                first = parts.asked_high + 1  # asked for too recently: only what is new
                next_s = min(next_s, parts.asked_s + hold)
            runs = parts.missing_runs(first, last) if first <= last else []
            if not runs:
                continue
            room = wire.MAX_FRAG_RANGES - len(asks)
            if len(runs) > room:
                runs, last = runs[:room], runs[room - 1][1]
            asks.extend((seq, lo, hi) for lo, hi in runs)
            if first == 0:
                parts.asked_s = now
            parts.asked_high = max(parts.asked_high, last)
            self.fragments_nacked += sum(hi - lo + 1 for lo, hi in runs)
            if len(asks) >= wire.MAX_FRAG_RANGES:
                break
        return asks, next_s

    def _in_order(self, p: _WriterProxy) -> bool:
        """Nothing pending for ``p``: the next expected samples can be delivered at once."""
        return p.synced and not p.buffer and not p.gaps and not self._lifespan_ns and p.lease.alive

    def _one(
        self, p: _WriterProxy, flags: int, seq: int, stamp: int, payload: bytes
    ) -> list[Action]:
        if seq == p.expected and self._in_order(p):
            return self._deliver_run(p, flags, seq, (stamp,), (payload,))
        return self._sample(p, wire.DataHeader(flags, p.guid, seq, stamp), payload)

    def _deliver_run(
        self,
        p: _WriterProxy,
        flags: int,
        first: int,
        stamps: Sequence[int],
        payloads: Sequence[bytes],
    ) -> list[Action]:
        """The common case, samples ``first, first + 1, ...`` in order with nothing pending:
        what ``_sample`` and ``_deliver`` do for each, once for the run (one clock read, one
        deadline reset, one ACKNACK if the last asks for it)."""
        now = self._mono()
        p.lease.last_s = now
        actions: list[Action] = []
        if p.deadline.period_s:
            self._deadline_met(p, now, actions)
        retransmitted = bool(flags & wire.F_RETRANSMIT)
        n = len(payloads)
        actions.append(DeliverRun(p.topic, p.hex, first, stamps, payloads, retransmitted))
        seq = first + n
        p.expected = seq
        seq -= 1
        if seq > p.highest:
            p.highest = seq
        if seq > p.confirmed_high:
            p.confirmed_high = seq
        self.delivered += n
        p.delivered += n
        if retransmitted:
            self.retransmitted += n
        if flags & wire.F_ACK_REQUEST and self._reliable:
            actions.append(self._acknack(p, now))
        return actions

    def on_directed(self, key: str, payload: bytes, attachment: bytes | None) -> list[Action]:
        split = wire.split_control_key(key, "rx", 1)
        if split is None:
            self.bad("directed message on a malformed key", key)
            return []
        topic = split[0]
        if attachment is not None and len(attachment) == wire.RESEND_FRAG.size:
            return self._on_fragment(topic, payload, attachment, "resent fragment")
        if attachment is not None:
            header = wire.decode_data(attachment)
            if header is None:
                self.bad("malformed resend", key)
                return []
            p = self._known_writer(topic, header.writer, "resend")
            return self._sample(p, header, payload) if p is not None else []
        kind = wire.control_kind(payload)
        if kind == wire.KIND_HEARTBEAT:
            return self._heartbeat(topic, key, payload)
        if kind == wire.KIND_GAP:
            gap = wire.decode_gap(payload)
            if gap is None or gap.reader != self.guid:
                self.bad("malformed or misdirected GAP", key)
                return []
            p = self._known_writer(topic, gap.writer, "GAP")
            return self._gap(p, gap.lost) if p is not None else []
        self.bad("unknown directed message", key)
        return []

    def _sample(self, p: _WriterProxy, h: wire.DataHeader, payload: bytes) -> list[Action]:
        seq = h.seq
        heard = self._heard(p, seq, h.echo, "sample")
        if heard is None:
            return []
        now, actions = heard
        if seq > p.confirmed_high:
            p.confirmed_high = seq
        if not self._reliable:
            if not p.synced:
                p.synced = True
                p.expected = p.start = seq
            if seq < p.expected:
                self.late += 1
                return actions
            if seq > p.expected:
                self._add_lost(p, seq - p.expected, actions)
            p.expected = seq + 1
            if p.partials:
                self._drop_samples_below(p, seq + 1)
            p.highest = max(p.highest, seq)
            self._deliver(p, seq, payload, h.stamp_ns, h.flags, now, actions)
            return actions
        if seq < p.expected or seq in p.buffer:
            self.duplicates += 1
            return actions
        if not p.synced:
            if len(p.buffer) < self._cap:
                p.buffer[seq] = (payload, h.stamp_ns, h.flags)
            else:  # NACKed again after SYNC if it belongs to the match
                self.bad("sample before SYNC beyond the buffer", seq, race=True)
            if seq > p.highest:
                p.highest = seq
            return actions
        if seq == p.expected:
            p.expected = seq + 1
            self._deliver(p, seq, payload, h.stamp_ns, h.flags, now, actions)
            if p.buffer or p.gaps:
                self._drain(p, actions)
        else:
            p.buffer[seq] = (payload, h.stamp_ns, h.flags)
            if p.partials:
                self._close_samples_before(p, seq, now)
            if seq > p.highest + 1:
                p.detect.append((seq - 1, now))
                p.an_due_s = min(p.an_due_s, now + self.qos.nack_delay_s)
            if len(p.buffer) > self._cap:
                self._skip_to(p, min(p.buffer), actions)
        if seq > p.highest:
            p.highest = seq
        if h.flags & wire.F_ACK_REQUEST:
            actions.append(self._acknack(p, now))
        return actions

    def _heard(
        self, p: _WriterProxy, seq: int, echo: int, what: str
    ) -> tuple[float, list[Action]] | None:
        """Writer ``p`` sent ``what`` (a sample or a fragment) of ``seq``: None when the seq is
        beyond its reach (refused, counted); else (now, actions) with the writer alive and the
        NACK its resend answers (``echo``) timed."""
        self._suspects.add(p)
        now = self.clock.monotonic_s()
        if p.synced and seq > self._seq_limit(p, now):  # before _alive: it resets the silence
            self.implausible += 1
            self.bad(f"{what} with an implausible seq", f"{p.topic} {seq}")
            return None
        if echo >= 0:
            self._measure_rtt(p, now, echo)
        actions: list[Action] = []
        self._alive(p, now, actions)
        return now, actions

    def _seq_limit(self, p: _WriterProxy, now: float) -> int:
        """The highest seq writer ``p`` can have written by now: one window past the highest seq
        it proved, plus what it could write at wire.MAX_WRITE_RATE_HZ since it was last heard."""
        silent_s = max(now - p.lease.last_s, 0.0)
        base = max(p.highest, p.expected - 1)
        return base + self._trust_window + int(wire.MAX_WRITE_RATE_HZ * silent_s)

    def _deliver(
        self,
        p: _WriterProxy,
        seq: int,
        payload: bytes,
        stamp_ns: int,
        flags: int,
        now: float,
        actions: list[Action],
    ) -> None:
        self._deadline_met(p, now, actions)
        if self._lifespan_ns and self.clock.wall_ns() - stamp_ns > self._lifespan_ns:
            self.lifespan_expired += 1
            p.expired += 1
            return
        retransmitted = bool(flags & wire.F_RETRANSMIT)
        self.retransmitted += retransmitted
        self.delivered += 1
        p.delivered += 1
        actions.append(Deliver(payload, DataInfo(p.topic, p.hex, seq, stamp_ns, retransmitted)))

    def _deadline_met(self, p: _WriterProxy, now: float, actions: list[Action]) -> None:
        self._count_missed(p, p.deadline.reset(now), actions)

    def _count_missed(self, p: _WriterProxy, missed: int, actions: list[Action]) -> None:
        if missed:
            self.deadline_missed += missed
            actions.append(
                Notify("deadline", DeadlineMissedStatus(self.deadline_missed, missed, p.hex))
            )

    def _add_lost(self, p: _WriterProxy, n: int, actions: list[Action]) -> None:
        if n <= 0:
            return
        p.lost += n
        self.lost += n
        actions.append(Notify("message_lost", MessageLostStatus(self.lost, n, p.hex)))

    def _drain(self, p: _WriterProxy, actions: list[Action]) -> None:
        now = self.clock.monotonic_s()
        while True:
            item = p.buffer.pop(p.expected, None)
            if item is not None:
                p.expected += 1
                self._deliver(p, p.expected - 1, item[0], item[1], item[2], now, actions)
                continue
            if p.gaps and p.gaps[0][0] <= p.expected:
                _, hi = p.gaps.pop(0)
                if hi >= p.expected:
                    self._skip_to(p, hi + 1, actions)
                continue
            break
        while p.detect and p.detect[0][0] < p.expected:
            p.detect.pop(0)
        if p.partials:
            self._drop_samples_below(p, p.expected)

    def _skip_to(self, p: _WriterProxy, target: int, actions: list[Action]) -> None:
        """Give up everything below ``target``: deliver what is buffered there, count the rest."""
        if target <= p.expected:
            return
        self._suspects.add(p)
        now = self.clock.monotonic_s()
        held = sorted(s for s in p.buffer if s < target)
        for seq in held:
            data, stamp, flags = p.buffer.pop(seq)
            self._deliver(p, seq, data, stamp, flags, now, actions)
        self._add_lost(p, target - p.expected - len(held), actions)
        p.expected = target
        if target - 1 > p.highest:
            p.highest = target - 1
        self._drain(p, actions)

    # ------------------------------------------------------------------ control
    def on_heartbeat(self, key: str, payload: bytes, attachment: bytes | None) -> list[Action]:
        split = wire.split_control_key(key, "hb", 1)
        if split is None:
            self.bad("HEARTBEAT on a malformed key", key)
            return []
        topic, (writer_hex,) = split
        return self._heartbeat(topic, key, payload, writer_hex)

    def _heartbeat(
        self, topic: str, key: str, payload: bytes, writer_hex: str | None = None
    ) -> list[Action]:
        """``writer_hex``: the writer named by the key (a multicast heartbeat's), which must be
        the one in the message (a directed one's key names the reader instead)."""
        hb = wire.decode_heartbeat(payload)
        if hb is None:
            self.bad("malformed HEARTBEAT", key)
            return []
        if writer_hex is not None and hb.writer.hex() != writer_hex:
            self.impersonations += 1
            self.bad("HEARTBEAT with another guid than its key's writer", key)
            return []
        p = self._known_writer(topic, hb.writer, "HEARTBEAT")
        if p is None:
            return []
        self._suspects.add(p)
        now = self.clock.monotonic_s()
        if p.synced and hb.last > self._seq_limit(p, now):
            self.implausible += 1
            self.bad("HEARTBEAT with an implausible last seq", f"{p.topic} {hb.last}")
            return []
        actions: list[Action] = []
        if not p.manual or hb.flags & wire.HB_LIVELINESS:
            self._alive(p, now, actions)
        if hb.flags & wire.HB_UNCHANGED:
            self.unchanged += 1
            self._deadline_met(p, now, actions)
            actions.append(
                Notify(
                    "unchanged",
                    UnchangedStatus(self.unchanged, p.topic, p.hex, self.clock.wall_ns()),
                )
            )
        sync = bool(hb.flags & wire.HB_SYNC)
        if not self._reliable:
            if sync:
                if not p.synced:
                    p.synced, p.expected, p.start = True, hb.first, hb.first
                elif not p.an_count and hb.first < p.start:
                    # Data overtook the SYNC: what the writer sent since the match start and we
                    # never saw is lost, not outside the match.
                    self._add_lost(p, p.start - hb.first, actions)
                    p.start = hb.first
                if not p.an_count:  # one ACKNACK so the writer stops repeating SYNC
                    actions.append(self._acknack(p, now))
            elif p.synced and hb.last >= p.expected:
                self._defer_loss(p, hb.last + 1, now)
            return actions
        if sync:
            if not p.synced:
                p.synced = True
                p.expected = p.start = hb.first
                p.highest = max(p.highest, hb.first - 1)
                early = [s for s in p.buffer if s < hb.first]
                for seq in early:
                    del p.buffer[seq]
                self.before_match += len(early)
                if p.highest >= p.expected:
                    # Seen before SYNC: what is missing up to the highest seq seen (data that
                    # overtook data, or samples beyond the pre-SYNC buffer, ignored then) is
                    # NACKed now. Up to max(buffer) only, the samples beyond the buffer were
                    # never asked for again (a late TRANSIENT_LOCAL reader that received a
                    # delayed batch before its SYNC missed them for good).
                    p.detect.append((p.highest, now))
            p.an_due_s = now
        elif not p.synced:
            return actions
        elif hb.first > p.expected:
            self._defer_loss(p, hb.first, now)
        if hb.first > p.held_from:
            p.held_from = hb.first
        if hb.last > p.announced:
            p.announced = hb.last
        if p.partials:  # the writer sent every sample up to hb.last: theirs are all out
            for seq, parts in p.partials.items():
                if seq <= hb.last:
                    self._close_sample(p, parts, now + self.qos.nack_period_s / 4)
        if hb.last > p.highest:
            # A heartbeat may overtake its data through a router: give the data a head start.
            p.detect.append((hb.last, now + self.qos.nack_period_s / 4))
            p.highest = hb.last
            p.an_due_s = min(p.an_due_s, now + self.qos.nack_delay_s)
        self._drain(p, actions)
        if not hb.flags & wire.HB_FINAL:
            p.an_due_s = now
        if p.an_due_s <= now:
            actions.append(self._acknack(p, now))
        return actions

    def _gap(self, p: _WriterProxy, ranges: list[tuple[int, int]]) -> list[Action]:
        self._suspects.add(p)
        actions: list[Action] = []
        if not p.synced:
            return actions
        for lo, hi in ranges:
            # a GAP may be forged too: it skips at most one window past what is proven
            hi = min(hi, p.highest, max(p.confirmed_high, p.expected) + self._cap)
            if hi > p.confirmed_high:
                p.confirmed_high = hi
            self.gaps += max(0, hi - max(lo, p.expected) + 1)
            if hi < p.expected:
                continue
            if lo <= p.expected:
                self._skip_to(p, hi + 1, actions)
            elif len(p.gaps) < wire.MAX_RANGES:
                bisect.insort(p.gaps, (lo, hi))
            else:  # the seqs stay missing: NACKed again, GAPed again
                self.bad("GAP range beyond the pending-range bound", (lo, hi))
        self._drain(p, actions)
        return actions

    def _nack_limit(self, p: _WriterProxy, now: float) -> tuple[int, float]:
        """The highest seq missing for at least nack_delay_s, and when the next run ripens.

        Waiting that long keeps a heartbeat that overtook its data (seen through a router) from
        triggering resends of samples that are only a few milliseconds behind.
        """
        ripe = now - self.qos.nack_delay_s
        upto, next_s = p.expected - 1, math.inf
        for run_end, seen_s in p.detect:
            if seen_s > ripe:
                next_s = seen_s + self.qos.nack_delay_s
                break
            if self.fifo_behind and seen_s > self.drained_s:
                # ripe by time, but what the channel's FIFO still holds may answer it: asked
                # again when it has drained past (``drained``), or a heartbeat period from now
                self._drain_waiters[p] = seen_s
                next_s = now + self.qos.heartbeat_period_s
                break
            upto = run_end
        return upto, next_s

    def drained(self, at_s: float) -> bool:
        """The channel's FIFO held nothing older than ``at_s`` (math.inf: it is empty and the
        channel waits on it). True when a NACK that waited for this is due now: tick soon."""
        self.drained_s = at_s
        waiters = self._drain_waiters
        if not waiters:
            return False
        ready = [p for p, seen_s in waiters.items() if seen_s <= at_s]
        if not ready:
            return False
        now = self.clock.monotonic_s()
        for p in ready:
            del waiters[p]
            if p.detect:  # still missing something: the ACKNACK decides what
                self._suspects.add(p)
                p.an_due_s = min(p.an_due_s, now)
        return True

    @property
    def drain_waited(self) -> bool:
        """Some NACK waits for the channel's FIFO to drain."""
        return bool(self._drain_waiters)

    def _missing(self, p: _WriterProxy, upto: int) -> list[tuple[int, int]]:
        ranges: list[tuple[int, int]] = []
        cur = p.expected
        held = sorted(p.buffer) if not p.partials else sorted({*p.buffer, *p.partials})
        for seq in [*held, p.highest + 1]:
            if cur > upto:
                break
            if seq > cur:
                ranges.append((cur, min(seq - 1, upto)))
                if len(ranges) >= wire.MAX_RANGES:
                    break
            cur = seq + 1
        return ranges

    def _nack_repeat_s(self, p: _WriterProxy) -> float:
        """Repeat an unanswered NACK after a few measured round trips, at most nack_period_s
        while the round trip is short: on a lossy link the NACK or the resend is often lost, and
        a fixed long period would turn every double loss into a long stall."""
        if p.srtt_s <= 0:
            return self.qos.nack_period_s
        repeat = max(0.002, 3 * p.srtt_s)
        if repeat > self.qos.nack_period_s:
            # a long round trip: no answer can come sooner than one, and repeating faster only
            # makes the writer resend what is already on its way (a restarted reader catching
            # up on a long TRANSIENT_LOCAL history over 100 ms resent it 4 times)
            repeat = max(self.qos.nack_period_s, 1.5 * p.srtt_s)
        return repeat

    def _nack_hold_s(self, p: _WriterProxy) -> float:
        """How long seqs once asked for are not asked for again: an answer time and a half,
        doubled (up to MAX_NACK_BACKOFF times) while the full NACKs before went unanswered, as
        TCP backs off its retransmission timeout. Before any answer is measured, nack_period_s
        stands in for it: a reader that joins a long history over a slow link asks for it once,
        not once per ack request of the live data until the first resend is back."""
        base = 1.5 * p.srtt_s if p.srtt_s > 0 else self.qos.nack_period_s
        return base * (1 << min(max(p.unanswered - 1, 0), MAX_NACK_BACKOFF))

    def _measure_rtt(self, p: _WriterProxy, now: float, echo: int) -> None:
        """Time the NACK a resend answers. Every resend of the answer measures it, so the
        smoothed time is that of a whole answer (up to RESEND_BUDGET resends, which a busy
        reader takes tens of milliseconds to take in), not of its first resend: asking again
        sooner than that asks for resends still on their way."""
        sent = p.nack_sent.get(echo)
        if sent is None:
            return
        sample = now - sent
        p.unanswered = 0
        p.srtt_s = sample if p.srtt_s <= 0 else 0.875 * p.srtt_s + 0.125 * sample

    def _acknack(self, p: _WriterProxy, now: float) -> Send:
        self._suspects.add(p)  # it sets the next ACKNACK's time
        upto, next_s = self._nack_limit(p, now)
        missing = self._missing(p, upto) if upto >= p.expected else []
        frags: Sequence[tuple[int, int, int]] = ()
        frags_next_s = math.inf
        if p.partials and self._reliable:
            frags, frags_next_s = self._fragment_nacks(p, now)
        held_until = math.inf
        if missing:
            hold = self._nack_hold_s(p)
            if self.queued:  # the answer may be among the samples still queued before us
                hold *= QUEUED_HOLD_FACTOR
            if now - p.nack_high_s < hold and missing[0][0] <= p.nack_high:
                # asked for too recently for an answer to be here: only what is new since
                held_until = p.nack_high_s + hold
                missing = [(max(lo, p.nack_high + 1), hi) for lo, hi in missing if hi > p.nack_high]
            else:
                p.nack_high, p.nack_high_s = missing[-1][1], now
                p.unanswered += 1
        p.an_count += 1
        if missing or frags:
            self.nacks += 1
            sent = p.nack_sent
            sent[p.an_count & 0xFFFFFFFF] = now
            if len(sent) > MAX_NACKS_TIMED:
                del sent[next(iter(sent))]
            p.an_due_s = min(now + self._nack_repeat_s(p), frags_next_s)
        else:
            self.acks += 1
            p.an_due_s = min(next_s, held_until, frags_next_s)
        payload = wire.encode_acknack(self.guid, p.guid, p.expected, p.an_count, missing, frags)
        return Send(p.an_key, payload)

    def tick(self, backlog: int = 0) -> list[Action]:
        """Timers. ``backlog``: samples still queued before this machine; while there are some,
        nothing is declared lost by time (the missing sample may be among them).

        Every writer's deadline and lease are polled once a ``_full_period_s``; the ticks in
        between (the fine timer, every few ms while any writer is busy) look only at the
        suspects, which hold every writer with a NACK, a loss or a departure pending. Polling
        all of a CEDDP's writers at every fine tick grew with the fleet: 400 writers, 500 ticks a
        second (issue 17)."""
        now = self.clock.monotonic_s()
        self.queued = backlog > 0
        actions: list[Action] = []
        gone: list[_WriterProxy] = []
        full = now >= self._next_full_s
        if full:  # a little early: the channel's idle tick (one period after) is then a full one
            self._next_full_s = now + 0.8 * self._full_period_s
            if self._away:
                self._expire_away(now, actions)
        for p in self.writers.values() if full else list(self._suspects):
            if not full and self.writers.get((p.topic, p.guid)) is not p:
                self._suspects.discard(p)  # unmatched since it became a suspect
                continue
            if p.leaving_s is not None:
                if now >= p.leaving_s and not backlog:
                    gone.append(p)
                continue
            if full:
                self._poll_timers(p, now, actions)
            if not p.synced:
                continue
            if not backlog:
                self._settle(p, now, actions)
                if self._reliable:
                    self._give_up(p, now, actions)
            if self._reliable and p.an_due_s <= now:
                actions.append(self._acknack(p, now))
        for p in gone:
            self._unmatch(p, now, actions)
        return actions

    def _poll_timers(self, p: _WriterProxy, now: float, actions: list[Action]) -> None:
        """Writer ``p``'s deadline and liveliness lease."""
        self._count_missed(p, p.deadline.poll(now), actions)
        if p.lease.poll(now):
            self.alive_count -= 1
            self.not_alive_count += 1
            actions.append(self._liveliness(-1, 1, p.hex))

    def _defer_loss(self, p: _WriterProxy, below: int, now: float) -> None:
        """A heartbeat says nothing below ``below`` will ever be (re)sent to us. Through a router
        a heartbeat can overtake the data it covers by milliseconds, so what is missing is
        declared lost only after nack_period_s, when it has had every chance to arrive."""
        self._suspects.add(p)
        if p.gone_below is None:
            p.gone_below = (below, now + self.qos.nack_period_s)
        elif below > p.gone_below[0]:
            p.gone_below = (below, p.gone_below[1])

    def _settle(self, p: _WriterProxy, now: float, actions: list[Action]) -> None:
        if p.gone_below is None or now < p.gone_below[1]:
            return
        below, p.gone_below = p.gone_below[0], None
        if self._reliable:
            # beyond what the writer proved it sent, NACKs (answered by resends or GAPs) decide
            below = min(below, p.confirmed_high + 1)
        else:  # no NACKs: trust a heartbeat up to one window past the data, no further
            below = min(below, p.confirmed_high + 1 + self._trust_window)
        if below <= p.expected:
            return
        if self._reliable:
            self._skip_to(p, below, actions)
        else:
            self._add_lost(p, below - p.expected, actions)
            p.expected = below
            if p.partials:
                self._drop_samples_below(p, below)

    def busy(self) -> bool:
        """Something is pending that needs the fine timer (a NACK, a loss to settle).

        Only the suspects are looked at, and those found idle leave the set: the in-order path
        (``_deliver_run``) never makes a writer busy but through ``_acknack``, so a stream in
        order costs nothing here however many writers the reader has. ``busy_scan`` is the
        definition, over every writer (the tests hold the two equal at every step)."""
        suspects = self._suspects
        if not suspects:
            return False
        idle = [p for p in suspects if not _pending(p)]
        suspects.difference_update(idle)
        return bool(suspects)

    def busy_scan(self) -> bool:
        """``busy`` by its definition: any matched writer with something pending."""
        return any(_pending(p) for p in self.writers.values())

    def _give_up(self, p: _WriterProxy, now: float, actions: list[Action]) -> None:
        """Bound head-of-line blocking: a run missing for reorder_timeout_s is declared lost,
        and so is a sample in assembly at the head whose fragments were all sent that long ago
        with later samples waiting behind it (KEEP_ALL: only once the writer no longer holds
        it, as for any sample)."""
        limit = now - self.qos.reorder_timeout_s
        while p.partials and p.highest > p.expected:
            parts = p.partials.get(p.expected)
            if parts is None or min(parts.closed_s, parts.gap_s) > limit:
                break
            if self._keep_all and p.expected >= p.held_from:
                break
            self._skip_to(p, p.expected + 1, actions)
        while p.highest >= p.expected and p.detect and p.detect[0][1] <= limit:
            run_end = p.detect[0][0]
            nxt = min(p.buffer) if p.buffer else p.highest + 1
            target = min(nxt, run_end + 1, p.confirmed_high + 1)
            if self._keep_all:
                # A KEEP_ALL reader waits for what the writer still holds (its last heartbeat's
                # first), as DDS does: a (re)joining reader receiving a long history must not
                # declare lost what is only queued behind it. The heartbeat declares the rest.
                target = min(target, p.held_from)
            if target <= p.expected:
                break  # nothing later is proven to exist: no head-of-line to unblock
            self._skip_to(p, target, actions)
            if p.detect and p.detect[0][0] < p.expected:
                p.detect.pop(0)

    def stats(self) -> ReaderStats:
        return ReaderStats(
            delivered=self.delivered,
            lost=self.lost,
            lifespan_expired=self.lifespan_expired,
            duplicates=self.duplicates,
            late=self.late,
            retransmitted=self.retransmitted,
            nacks=self.nacks,
            acks=self.acks,
            gaps=self.gaps,
            unchanged=self.unchanged,
            deadline_missed=self.deadline_missed,
            matched=len(self.writers),
            incompatible=self.incompatible,
            before_match=self.before_match,
            bad_input=self.bad.total(),
            plain_refused=sum(self.plain_samples.values()),
            impersonations=self.impersonations,
            implausible=self.implausible,
            writers_refused=self.writers_refused,
            resumed=self.resumed,
            away=len(self._away),
            fragments_received=self.fragments_received,
            fragments_duplicate=self.fragments_duplicate,
            fragments_refused=self.fragments_refused,
            samples_too_large=self.samples_too_large,
            fragments_nacked=self.fragments_nacked,
            in_assembly=sum(len(p.partials) for p in self.writers.values()),
            assembly_bytes=self._assembly_bytes,
        )

    def accounted(self) -> dict[str, tuple[int, int, int, int, int]]:
        """Per matched writer (guid hex): (first seq of the match, last seq accounted for, and
        of those: delivered, declared lost, dropped past their lifespan). The writer side
        reconciles against it: the count of each seq between the first and the last. A writer
        away (its session lost) is still accounted: its match may resume."""
        away = (p for p, _ in self._away.values())
        return {
            p.hex: (p.start, p.expected - 1, p.delivered, p.lost, p.expired)
            for p in (*self.writers.values(), *away)
            if p.synced
        }

    def round_trips(self) -> dict[str, float]:
        """Per matched writer's topic key: the smoothed NACK -> resend round trip this reader
        measured, in seconds (writers never asked to resend have none yet). The CEDDP's QoS
        loop reads each robot's link from it (docs/qos-optimiser.md)."""
        return {p.topic: p.srtt_s for p in self.writers.values() if p.srtt_s > 0}

    def match_start(self, writer_hex: str) -> int | None:
        """Where the match with this writer started, for tests of the invariant."""
        for p in self.writers.values():
            if p.hex == writer_hex and p.synced:
                return p.start
        return None
