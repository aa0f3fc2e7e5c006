"""The writer side of the reliable protocol as a pure state machine: values in, actions out.

The history is contiguous (``first .. last_seq``) because samples only ever leave from the front
(acknowledged by every reliable reader, overwritten by KEEP_LAST, or past their lifespan), so a
resend request is answered by index and everything below ``first`` is answered with one GAP.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

import msgspec

from arpz.core.errors import ArpzError
from arpz.core.protocol import wire
from arpz.core.protocol._common import AWAY_RETENTION_S, BadInput, parse_token
from arpz.core.protocol.actions import Action, Notify, Send
from arpz.core.protocol.events import (
    DeadlineMissedStatus,
    IncompatibleQosStatus,
    LivelinessLostStatus,
    MatchedStatus,
    MessageLostStatus,
)
from arpz.core.protocol.fragments import DEFAULT_FRAGMENT_BYTES, fragment_count
from arpz.core.protocol.qos import (
    HistoryPolicy,
    LivelinessPolicy,
    QosProfile,
    encode_match_qos,
    incompatible_policy,
    rounded,
)
from arpz.core.protocol.timers import Clock, DeadlineTimer, LeaseTimer

#: resends answered per ACKNACK: bounds the work of one (possibly forged) request; the reader
#: asks again for the rest one NACK period later
RESEND_BUDGET = 256
#: a seq NACKed again within this long of its resend to the same reader is not resent: the copy
#: is still on its way. Short enough that a lost resend on WiFi is repeated within ~2 round
#: trips; the reader, for its part, does not ask again within one measured answer time
#: (reader_machine._nack_hold_s)
RESEND_HOLDOFF_S = 0.01
#: the holdoff until a first resend to a reader is confirmed: a reader that joins a long history
#: asks for it again before the first burst is in, as it has no answer time to go by yet (with
#: 10 ms, the first 256 of each topic's history went out twice: the resends printed by
#: ``python -m pytest tests/integration/test_faults.py -s -k high_rate``)
RESEND_FIRST_HOLDOFF_S = 0.05
#: fragments resent per ACKNACK (a whole sample's when none of it arrived, or the ones an
#: ACKNACK_FRAG names), in bytes: 2 MiB, so a 921 600-byte camera frame lost whole goes out again
#: in one answer; the reader asks again for the rest
FRAGMENT_RESEND_BYTES = 2 * 2**20
#: without reliable readers, acknowledged-by-nobody samples are dropped in batches of this size
_PURGE_EVERY = 64
#: what ``write`` returns when it has no actions (most writes): nothing allocated per write
_NO_ACTIONS: tuple[Action, ...] = ()
#: heartbeat periods after a reader's last NACK during which every periodic heartbeat goes out,
#: even on a streaming topic whose data asked for (and got) an acknowledgement
LOSSY_HOLD_PERIODS = 50
#: a batch goes out once its payloads reach this size, whatever ``batch_max_samples`` says: with
#: its attachment (at most 20 + 12 x 1024 bytes) it stays within one Zenoh transport batch
#: (65 535 bytes), so Zenoh never has to fragment it
BATCH_MAX_BYTES = 48 * 1024


#: the longest a quiet writer's heartbeat timer sleeps (``WriterMachine._go_quiet``); the
#: driver's idle period (``arpz.channel._channel.MAX_IDLE_S``) is this one
QUIET_HEARTBEAT_S = 1.0


class HistoryFullError(ArpzError, TimeoutError):
    """KEEP_ALL history full of samples some reader has not acknowledged."""


class WriterStats(msgspec.Struct, frozen=True):
    sent: int
    retransmitted: int
    #: sequence numbers NACKed by readers
    nacks: int
    #: sequence numbers answered with GAP (no longer held)
    gaps: int
    heartbeats: int
    #: samples a reader asked for that were no longer held (answered by GAP): lost for sure
    lost: int
    #: KEEP_LAST overwrote a sample some matched reliable reader had not yet acknowledged
    #: (an upper bound of the losses: a reader may have it without having acknowledged it yet)
    overwritten_unacked: int
    lifespan_expired: int
    unchanged: int
    deadline_missed: int
    liveliness_lost: int
    matched: int
    incompatible: int
    history: int
    bad_input: int
    #: refused by the full worker queue (reliable readers get them again by NACK)
    queue_dropped: int = 0
    #: exceptions raised by user callbacks (logged, the channel goes on)
    callback_errors: int = 0
    #: NACKed seqs not resent because their resend to that reader was still on its way
    resends_held_off: int = 0
    #: samples the history held when a reliable TRANSIENT_LOCAL reader matched, summed over
    #: matches: what late joiners could ask for, so resends can be judged against it
    history_offered: int = 0
    #: matches that went on after the reader's token came back (its session was lost and
    #: reopened) instead of starting again
    resumed: int = 0
    #: readers away now: token gone, state kept for AWAY_RETENTION_S in case they come back
    away: int = 0
    #: periodic heartbeats left out because a DATA asking for an acknowledgement had done their
    #: work since the previous one (a streaming topic; see ``WriterMachine.tick``)
    heartbeats_piggybacked: int = 0
    #: samples larger than the fragment size, sent as fragments (each still one seq in ``sent``)
    fragmented: int = 0
    #: their fragments as first sent, and the fragments resent (a lost whole sample's, or the
    #: ones an ACKNACK_FRAG asked for; also in ``retransmitted``, one per fragment)
    fragments_sent: int = 0
    fragments_retransmitted: int = 0
    #: fragments readers asked for by ACKNACK_FRAG
    fragments_nacked: int = 0


class _ReaderProxy:
    """The writer's view of one matched reader."""

    __slots__ = (
        "acked",
        "guid",
        "hex",
        "last_sync_s",
        "lost",
        "reliable",
        "requested_deadline_s",
        "resend_confirmed",
        "resent",
        "resent_frags",
        "rx_key",
        "start",
        "synced",
    )

    def __init__(self, guid: bytes, hex_: str, reliable: bool, start: int, rx_key: str) -> None:
        self.guid, self.hex, self.reliable = guid, hex_, reliable
        self.start = start
        #: every seq below this is acknowledged (or outside the match)
        self.acked = start
        self.synced = False
        self.last_sync_s = -math.inf
        self.lost = 0
        self.rx_key = rx_key
        #: the deadline this reader checks (0: none), from its token
        self.requested_deadline_s = 0.0
        #: seq -> (when it was first resent to this reader, when last), unacknowledged seqs only
        self.resent: dict[int, tuple[float, float]] = {}
        #: (seq, fragment index) -> when last resent to this reader, unacknowledged seqs only
        self.resent_frags: dict[tuple[int, int], float] = {}
        #: a resend to this reader was acknowledged: it has an answer time of its own now
        self.resend_confirmed = False

    def holdoff_s(self) -> float:
        return RESEND_HOLDOFF_S if self.resend_confirmed else RESEND_FIRST_HOLDOFF_S

    def confirmed(self, floor: int) -> None:
        """Every resent seq below ``floor`` is acknowledged: forget it."""
        done = [s for s in self.resent if s < floor]
        for seq in done:
            del self.resent[seq]
        if done:
            self.resend_confirmed = True
        if self.resent_frags:
            frags = [k for k in self.resent_frags if k[0] < floor]
            for key in frags:
                del self.resent_frags[key]
            if frags:  # a resent fragment's sample was acknowledged: the holdoff is the short one
                self.resend_confirmed = True


#: readers whose state a writer keeps while they are away (the oldest forgotten first)
MAX_AWAY_READERS = 64


class WriterMachine:
    def __init__(
        self,
        topic: str,
        qos: QosProfile,
        guid: bytes,
        clock: Clock,
        *,
        away_retention_s: float = AWAY_RETENTION_S,
        fragment_bytes: int = DEFAULT_FRAGMENT_BYTES,
    ) -> None:
        self.topic = wire.check_topic_key(topic)
        if fragment_bytes < 1:
            raise ValueError(f"fragment_bytes must be >= 1, got {fragment_bytes}")
        #: a sample longer than this goes as fragments of this size (``write_large``)
        self.fragment_bytes = fragment_bytes
        #: the seq whose fragments the driver is putting now (0: none): heartbeats announce
        #: only the seqs before it, so that no reader asks for fragments still on their way
        self.fragmenting = 0
        self.fragmented = self.fragments_sent = self.fragments_retransmitted = 0
        self.fragments_nacked = 0
        self._frag_budget = max(1, FRAGMENT_RESEND_BYTES // fragment_bytes)
        self.away_retention_s = away_retention_s
        #: readers whose token vanished, by guid, with when their state expires (insertion
        #: order is expiry order). A reader whose session was lost comes back with the same
        #: guid: its match resumes where it acknowledged, so nothing goes to it twice and what
        #: was written in the gap is resent or GAPed (issue 39). Away readers hold no history
        #: back: a KEEP_ALL writer does not block on a reader that may never return.
        self._away: dict[bytes, tuple[_ReaderProxy, float]] = {}
        self.resumed = 0
        self.qos = qos
        self.guid = guid
        self.hex = guid.hex()
        self.clock = clock
        self.bad = BadInput(f"writer {topic} {self.hex}")
        self._offered = rounded(qos)
        self._capacity = qos.capacity
        self._keep_all = qos.history is HistoryPolicy.KEEP_ALL
        #: only KEEP_ALL VOLATILE drops acknowledged samples (see ``_purge``)
        self._purges = self._keep_all and not qos.transient_local
        self._manual = qos.liveliness is LivelinessPolicy.MANUAL_BY_TOPIC
        self._ack_interval = self._ack_interval_for(self._capacity)
        now = clock.monotonic_s()
        #: seq -> (payload, stamp_ns); holds exactly first .. last_seq
        self.history: dict[int, tuple[bytes, int]] = {}
        self.first = 1
        self.last_seq = 0
        self._last_ack_request = 0
        #: the next DATA asks for an acknowledgement (set when the heartbeat timer fires), and
        #: one did since the timer last fired: the heartbeat rides on the data stream
        self._ack_on_next_write = False
        self._ack_requested_since_hb = False
        #: the seq of the last DATA that asked for an acknowledgement
        self._ack_request_seq = 0
        #: when a reader last NACKed something (monotonic s): the link loses, keep heartbeats
        self._last_nack_s = -math.inf
        self.heartbeats_piggybacked = 0
        self.proxies: dict[bytes, _ReaderProxy] = {}
        self._incompatible: set[bytes] = set()
        self._hb_count = 0
        self._next_hb_s = now
        #: the heartbeat period in force: ``heartbeat_period_s``, grown while the writer is
        #: calm (``QosProfile.heartbeat_backoff``; ``tick``)
        self._hb_interval_s = qos.heartbeat_period_s
        #: the heartbeat timer found nothing to say: it sleeps until the next write, match or
        #: NACK re-arms it (``_rearm``), or ``QUIET_HEARTBEAT_S``
        self.quiet = False
        #: ``last_seq`` when a FINAL heartbeat (every reliable reader acknowledged everything)
        #: last went out; -1 after anything else. See ``_heartbeat_due``.
        self._final_hb_at = -1
        self._last_unchanged_hb_s = -math.inf
        self._last_live_hb_s = -math.inf
        self._asserted_since_hb = True
        self._deadline = DeadlineTimer(qos.deadline_s, now)
        self._lease = LeaseTimer(qos.lease_duration_s if self._manual else 0.0, now)
        self._hb_key = wire.heartbeat_key(topic, self.hex)
        self._mono = clock.monotonic_s
        self._wall_ns = clock.wall_ns
        self._pack = wire.DATA.pack
        #: deadline or manual liveliness: only then does a write need the time
        self._timed = qos.deadline_s > 0 or self._manual
        #: matched reliable readers
        self.n_reliable = 0
        #: advances whenever ``acknowledged_through`` may have changed but by a write (a reader
        #: acknowledged, matched or left, an overwrite moved a reader on): a caller that asks
        #: once a sample can keep the last answer while it stands (``Writer``). With no
        #: reliable reader every write changes the answer, and the epoch says nothing
        self.ack_epoch = 0
        #: write batching: payloads written but not yet sent (seq from ``last_seq - len(batch) +
        #: 1``) and their stamps; kept apart from the history, which may overwrite them
        self.batch: list[bytes] = []
        self._batch_stamps: list[int] = []
        self._batch_max = qos.batch_max_samples
        self._batch_delay_s = qos.batch_max_delay_s
        self._batch_flags = 0
        self._batch_bytes = 0
        self._batch_opened_s = 0.0
        self._last_put_s = -math.inf
        #: the first seq its publisher holds back (0: none), set by the driver before the put
        #: and cleared once the message left: a robot's bundle leaves when its tick ends, and a
        #: heartbeat the worker sent meanwhile announced seqs the reader could only NACK. On a
        #: starved robot that came later than the reader's head start for data behind a
        #: heartbeat, and every such NACK brought a duplicate (25 robots: 300-1 200 of each a
        #: run, against 11-19 NACKs without bundles; issue 17). Heartbeats and SYNC announce up
        #: to the seq before it.
        self.held_from = 0
        self.token_key = wire.writer_token(topic, self.hex, encode_match_qos(qos))
        self.retransmitted = self.nacks = self.gaps = self.heartbeats = 0
        #: NACKed seqs not resent because their resend to that reader was still on its way
        self.resends_held_off = 0
        self.history_offered = 0
        self.lost = self.lifespan_expired = self.unchanged = self.overwritten_unacked = 0
        self.liveliness_lost = self.incompatible = 0
        self.matched_total = 0

    def _ack_interval_for(self, capacity: int) -> int:
        """Samples between two ACK_REQUESTs: often enough that the history never fills while
        acknowledgements are on their way, rarely enough to cost little at high rates."""
        if self._keep_all:
            return max(1, min(1024, capacity // 4))
        return max(1, min(64, capacity // 2))

    # ------------------------------------------------------------------ routing
    def subscriptions(self) -> list[tuple[str, str]]:
        """(key expression, handler name) pairs the driver must subscribe."""
        return [(wire.acknack_key(self.topic, self.hex, "*"), "on_acknack")]

    def watch_expr(self) -> str:
        return wire.reader_token(self.topic, "*", "*")

    # ------------------------------------------------------------------ writing
    def _min_acked(self) -> int:
        acked = self.last_seq + 1
        for p in self.proxies.values():
            if p.reliable and p.acked < acked:
                acked = p.acked
        return acked

    def _min_acked_kept(self) -> int:
        """``_min_acked`` with the away readers too: what a purge keeps for them to come back
        to. They never block a write: a full KEEP_ALL history drops its front for them (they
        get a GAP when back), it waits only for the readers present."""
        acked = self._min_acked()
        for p, _ in self._away.values():
            if p.reliable and p.acked < acked:
                acked = p.acked
        return acked

    def _purge(self) -> None:
        """KEEP_ALL VOLATILE: drop what every reliable reader acknowledged, to make room.

        KEEP_LAST keeps its last ``depth`` samples whatever the acknowledgements say (as DDS
        does): they cost nothing more than the bound already allows, a reader whose ACKNACK was
        optimistic (or forged) can still get them again, and no purge runs per ACKNACK."""
        if self.qos.transient_local or not self._keep_all:
            return
        limit = self._min_acked_kept()
        if limit > self.last_seq:
            self.history.clear()
            self.first = self.last_seq + 1
            return
        while self.first < limit:
            del self.history[self.first]
            self.first += 1

    def all_acknowledged(self) -> bool:
        return self._min_acked() > self.last_seq and all(p.synced for p in self.proxies.values())

    def acknowledged_through(self) -> int:
        """The highest seq every matched reliable reader acknowledged, and all before it."""
        return self._min_acked() - 1

    def latest_undeliverable(self) -> bool:
        """The last sample written is gone from the history (lifespan, a purge) while some
        reliable reader has not acknowledged it: that reader can never get the newest value.
        Overwrites and GAPs never do this alone: they only drop samples a newer one superseded,
        and the newest stays held until it is acknowledged or expires."""
        last = self.last_seq
        return last > 0 and last not in self.history and self._min_acked() <= last

    def has_room(self) -> bool:
        if len(self.history) < self._capacity or not self._keep_all:
            return True
        return self.first < self._min_acked()  # the readers present only (_min_acked_kept)

    def write(
        self, payload: bytes, stamp_ns: int | None = None
    ) -> tuple[int, tuple[bytes, bytes] | None, Sequence[Action]]:
        """Assign the next seq, keep the sample, and return (seq, (payload, attachment) to
        publish on the topic key now or None, actions). Raises HistoryFullError if KEEP_ALL has no
        room (the driver waits for acknowledgements and retries up to max_blocking_time).

        Without batching every sample is published at once. With batching, a sample written
        ``batch_max_delay_s`` or more after the last message went out is published at once and
        alone; otherwise it joins the open batch, which is returned when full or when its oldest
        sample has waited ``batch_max_delay_s`` (here or from ``tick``), else None.

        This is the hot path of a publisher: everything that can be decided once is decided in
        ``__init__`` or on (un)matching, not here."""
        if self.quiet:
            self._rearm(self._mono())
        history = self.history
        actions: Sequence[Action] = _NO_ACTIONS
        if len(history) >= self._capacity:
            if self._keep_all:
                if self.first >= self._min_acked():
                    raise HistoryFullError(self._full_message())
                self._drop_front()
            else:
                overwritten: list[Action] = []
                self._overwrite_front(overwritten)
                actions = overwritten
        if stamp_ns is None:
            stamp_ns = self._wall_ns()
        seq = self.last_seq = self.last_seq + 1
        history[seq] = (payload, stamp_ns)
        flags = 0
        if self.n_reliable and (
            self._ack_on_next_write or seq - self._last_ack_request >= self._ack_interval
        ):
            flags = wire.F_ACK_REQUEST
            self._last_ack_request = seq
            self._ack_on_next_write = False
            self._ack_requested_since_hb = True
            self._ack_request_seq = seq
        if self._timed:  # deadline or manual liveliness: only then does a write need the time
            timed: list[Action] = list(actions)
            actions = timed
            now = self._mono()
            self._asserted_since_hb = True
            self._deadline_met(now, timed)
            self._lease.assert_alive(now)
        if not self.n_reliable and self._purges and len(history) >= _PURGE_EVERY:
            self._purge()  # nobody needs these; amortised, not on every write
        if self._batch_max == 1:
            return (
                seq,
                (payload, self._pack(wire.VERSION, flags, self.guid, seq, stamp_ns)),
                actions,
            )
        now = self._mono()
        batch = self.batch
        if not batch:
            if now - self._last_put_s >= self._batch_delay_s:
                self._last_put_s = now
                attachment = self._pack(wire.VERSION, flags, self.guid, seq, stamp_ns)
                return seq, (payload, attachment), actions
            self._batch_opened_s = now
        elif self._batch_bytes + len(payload) > BATCH_MAX_BYTES:
            # the open batch goes out without this sample, which opens the next one: one large
            # sample never makes a message outgrow a Zenoh batch (and get fragmented)
            ready = self._take_batch(now, held_back=1)
            self._batch_opened_s = now
            self.batch.append(payload)
            self._batch_stamps.append(stamp_ns)
            self._batch_flags = flags
            self._batch_bytes = len(payload)
            return seq, ready, actions
        batch.append(payload)
        self._batch_stamps.append(stamp_ns)
        if flags:
            self._batch_flags |= flags
        self._batch_bytes += len(payload)
        if (
            len(batch) >= self._batch_max
            or self._batch_bytes >= BATCH_MAX_BYTES
            or now - self._batch_opened_s >= self._batch_delay_s
        ):
            return seq, self._take_batch(now), actions
        return seq, None, actions

    def write_large(
        self, payload: bytes, stamp_ns: int | None = None
    ) -> tuple[int, list[tuple[bytes, bytes]], Sequence[Action]]:
        """``write`` for a sample longer than ``fragment_bytes``: it is kept whole in the
        history under one seq, as any other, and published as DATA_FRAG fragments of
        ``fragment_bytes`` (never batched: each fits one datagram). Returns (seq, messages to put
        on the topic key in order: the open batch first, if any, then every fragment, actions).
        Every fragment asks for an acknowledgement, which the reader gives once the sample is
        whole: one ACKNACK a large sample. Raises HistoryFullError as ``write`` does."""
        batch_max, self._batch_max = self._batch_max, 1
        try:  # the write itself, unbatched; the open batch (older seqs) leaves first
            seq, whole, actions = self.write(payload, stamp_ns)
        finally:
            self._batch_max = batch_max
        assert whole is not None
        flags = whole[1][1] | (wire.F_ACK_REQUEST if self.n_reliable else 0)
        now = self._mono()
        messages = [self._take_batch(now, held_back=1)] if self.batch else []
        self._last_put_s = now
        fragments = list(self._fragments(seq, payload, self.history[seq][1], flags))
        self.fragmented += 1
        self.fragments_sent += len(fragments)
        messages += fragments
        return seq, messages, actions

    def _fragments(
        self,
        seq: int,
        payload: bytes,
        stamp_ns: int,
        flags: int,
        first: int = 0,
        last: int | None = None,
        echo: int = -1,
    ) -> Iterator[tuple[bytes, bytes]]:
        """(payload, attachment) of fragments ``first .. last`` of sample ``seq`` (a resend's
        when ``echo`` >= 0, the count of the ACKNACK it answers)."""
        chunk, total, guid = self.fragment_bytes, len(payload), self.guid
        count = fragment_count(total, chunk)
        end = count - 1 if last is None else min(last, count - 1)
        for index in range(first, end + 1):
            start = index * chunk
            data = payload[start : start + chunk]
            if echo < 0:
                att = wire.encode_data_frag(flags, guid, seq, stamp_ns, index, total, chunk)
            else:
                att = wire.encode_resend_frag(guid, seq, stamp_ns, index, total, chunk, echo)
            yield data, att

    def flush_batch(self, force: bool) -> tuple[bytes, bytes] | None:
        """The open batch as (payload, attachment) if it is due (or ``force``), else None."""
        if not self.batch:
            return None
        now = self._mono()
        if not force and now - self._batch_opened_s < self._batch_delay_s:
            return None
        return self._take_batch(now)

    def _take_batch(self, now: float, held_back: int = 0) -> tuple[bytes, bytes]:
        """The open batch as one message; ``held_back`` samples written after it (the newest
        seqs) are not in it."""
        batch, stamps, flags = self.batch, self._batch_stamps, self._batch_flags
        first = self.last_seq - held_back - len(batch) + 1
        self.batch, self._batch_stamps = [], []
        self._batch_flags = self._batch_bytes = 0
        self._last_put_s = now
        if len(batch) == 1:
            return batch[0], self._pack(wire.VERSION, flags, self.guid, first, stamps[0])
        return wire.encode_batch(flags, self.guid, first, batch, stamps)

    @property
    def batch_due_s(self) -> float:
        """When the open batch must go out (monotonic s)."""
        return self._batch_opened_s + self._batch_delay_s

    @property
    def _last_sent(self) -> int:
        """The last seq put on the wire (written samples still in the open batch, or held by
        the publisher, are not)."""
        last = self.last_seq - len(self.batch)
        held = self.held_from
        if self.fragmenting:
            held = min(held, self.fragmenting) if held else self.fragmenting
        return last if not held else min(last, held - 1)

    def retune(
        self, *, depth: int, deadline_s: float, heartbeat_period_s: float | None = None
    ) -> list[Action]:
        """Apply a new KEEP_LAST depth and offered deadline in place (the CEDDP's QoS balancing),
        keeping the guid, the history and the matches: replacing the writer instead would make
        readers drop what it sends until they match it again. A smaller depth overwrites the
        oldest samples exactly as a write would, and counts them the same way. The deadline
        changes the writer's own timer; readers already matched stay matched (arpz's fleet
        reader requests no deadline, so no offer can become incompatible with it).

        ``heartbeat_period_s`` (None: unchanged) paces the recovery of a lost last sample, which
        only a heartbeat reveals: the closed QoS loop shortens it on a link measured lossy. A
        shorter period takes effect at once, not after the heartbeat already scheduled."""
        heartbeat = (
            self.qos.heartbeat_period_s if heartbeat_period_s is None else heartbeat_period_s
        )
        self.qos = msgspec.structs.replace(
            self.qos, depth=depth, deadline_s=deadline_s, heartbeat_period_s=heartbeat
        )
        QosProfile.__post_init__(self.qos)  # the same validation as a profile built from TOML
        self._capacity = self.qos.capacity
        self._ack_interval = self._ack_interval_for(self._capacity)
        actions: list[Action] = []
        while not self._keep_all and len(self.history) > self._capacity:
            self._overwrite_front(actions)
        now = self._mono()
        self._hb_interval_s = heartbeat
        self._next_hb_s = min(self._next_hb_s, now + heartbeat)
        self.quiet = False
        self._deadline = DeadlineTimer(deadline_s, now)
        self._timed = deadline_s > 0 or self._manual
        return actions

    def _full_message(self) -> str:
        waiting = [p.hex for p in self.proxies.values() if p.reliable and p.acked <= self.first]
        return (
            f"KEEP_ALL history of {self.topic} is full ({len(self.history)} samples = max_samples) "
            f"and reader(s) {', '.join(waiting) or '?'} have not acknowledged seq {self.first} "
            f"within max_blocking_time_s={self.qos.max_blocking_time_s}: the link is too slow or "
            "down; raise max_samples/max_blocking_time_s, lower the rate, or use KEEP_LAST"
        )

    def _drop_front(self) -> None:
        del self.history[self.first]
        self.first += 1

    def _overwrite_front(self, actions: list[Action]) -> None:
        """KEEP_LAST is full: the oldest goes. Whether a reader still needed it is known only
        when it NACKs it (then it gets a GAP and both sides count it lost); until then it is
        counted as ``overwritten_unacked``, an upper bound of the losses this write causes."""
        seq = self.first
        self._drop_front()
        for p in self.proxies.values():
            if p.reliable and seq >= p.acked:
                self.overwritten_unacked += 1
                p.acked = seq + 1
                self.ack_epoch += 1

    def _assert(self, now: float) -> None:
        self._asserted_since_hb = True
        self._lease.assert_alive(now)  # regaining liveliness has no ROS 2 writer event

    def assert_unchanged(self) -> list[Action]:
        """The local cache held back a reading equal to the last one sent: the topic is alive and
        its value current. Resets the offered deadline here and, through a heartbeat flagged
        UNCHANGED (at most one per third of the shortest deadline a reader requests, else one per
        heartbeat period), the requested deadline at every reader."""
        now = self.clock.monotonic_s()
        self.unchanged += 1
        actions: list[Action] = []
        self._deadline_met(now, actions)
        self._assert(now)
        # a reader checks at most the deadline it requested, so UNCHANGED heartbeats go at a third
        # of the shortest requested deadline (a third, not a half: margin for a loaded host or a
        # lost heartbeat); with no reader checking one, at the heartbeat period (one every
        # held-back reading would cost more than sending the data the cache saved)
        requested = [
            p.requested_deadline_s for p in self.proxies.values() if p.requested_deadline_s
        ]
        interval = min(requested) / 3 if requested else self.qos.heartbeat_period_s
        if self.proxies and self._min_acked() <= self.last_seq:
            # the last value sent is not acknowledged yet and the cache now holds its repeats
            # back: if it was lost, only a heartbeat reveals it, and the reader would plan on the
            # value before it until then. Announce it at the held-back readings until it is
            # acknowledged, at most once per NACK delay (the reader's own reaction time): about a
            # round trip's worth of small messages per change, and a burst costs one
            interval = min(interval, self.qos.nack_delay_s)
        if now - self._last_unchanged_hb_s < interval:
            return actions
        self._last_unchanged_hb_s = now
        actions.append(self._heartbeat(now, wire.HB_UNCHANGED))
        return actions

    def _deadline_met(self, now: float, actions: list[Action]) -> None:
        missed = self._deadline.reset(now)
        if missed:
            actions.append(Notify("deadline", DeadlineMissedStatus(self._deadline.total, missed)))

    def assert_liveliness(self) -> list[Action]:
        """MANUAL_BY_TOPIC: prove the writer alive without writing."""
        now = self.clock.monotonic_s()
        self._assert(now)
        lease = self.qos.lease_duration_s
        if lease > 0 and now - self._last_live_hb_s >= lease / 4:
            return [self._heartbeat(now, 0)]
        return []

    @property
    def next_heartbeat_s(self) -> float:
        """When the periodic heartbeat timer next fires (monotonic s): its driver wakes then."""
        return self._next_hb_s

    def _heartbeat_due(self, now: float) -> bool:
        """Whether the periodic heartbeat has anything to say. Once every reader is reliable,
        in sync and acknowledged everything, a writer that writes nothing goes quiet (as RTPS
        writers do): the next write, a new reader or a liveliness lease (every lease/4) makes it
        speak again. Best-effort readers learn the tail only from heartbeats, so they keep them
        coming. Going quiet halved what a fleet of quiet robots costs its CEDDP (26.8 -> 12.4 ms
        of CPU per robot a second, ``python benchmarks/fleet_scaling.py``; docs/performance.md).
        A write acknowledged before the next period (its DATA asked for it) needs no heartbeat
        at all: a FINAL one would tell readers only what their own ACKNACK said (a 1 Hz stream
        sent one after every sample: tests/unit/reliability/test_machines.py, issue 17)."""
        if self.batch:
            return True
        if any(not (p.reliable and p.synced) for p in self.proxies.values()):
            return True
        if self._final_hb_at != self.last_seq and (
            not self.proxies or self._min_acked() <= self.last_seq
        ):
            return True
        lease = self.qos.lease_duration_s
        return lease > 0 and now - self._last_live_hb_s >= lease / 4

    def _heartbeat(self, now: float, extra: int) -> Send:
        flags = extra
        if not self._manual or self._asserted_since_hb:
            flags |= wire.HB_LIVELINESS
            self._last_live_hb_s = now
        self._asserted_since_hb = False
        if self._min_acked() > self.last_seq:
            flags |= wire.HB_FINAL
        final = (
            flags & wire.HB_FINAL and not self.batch and not self.held_from and not self.fragmenting
        )
        self._final_hb_at = self.last_seq if final else -1
        self._hb_count += 1
        self.heartbeats += 1
        last = self._last_sent
        # with a batch open, KEEP_LAST may hold nothing already sent: announce an empty range
        payload = wire.encode_heartbeat(
            flags, self.guid, min(self.first, last + 1), last, self._hb_count
        )
        return Send(self._hb_key, payload)

    def _sync(self, p: _ReaderProxy, now: float) -> Send:
        """Tell one reader where its match starts (VOLATILE: the next seq; TRANSIENT_LOCAL: the
        oldest held), repeated until the reader's first ACKNACK proves it knows."""
        p.last_sync_s = now
        payload = wire.encode_heartbeat(
            wire.HB_SYNC | wire.HB_LIVELINESS,
            self.guid,
            p.start,
            max(self._last_sent, p.start - 1),  # matched while a batch was open: empty so far
            self._hb_count,
        )
        return Send(p.rx_key, payload)

    # ------------------------------------------------------------------ matching
    def on_reader_token(self, key: str, alive: bool) -> list[Action]:
        parsed = parse_token(key, "r", self.topic)
        if parsed is None:
            self.bad("malformed reader token", key)
            return []
        _, guid, hex_, mq = parsed
        now = self.clock.monotonic_s()
        self._expire_away(now)
        if not alive:
            self._incompatible.discard(guid)
            p = self.proxies.pop(guid, None)
            if p is None:
                return []
            self.n_reliable -= p.reliable
            self.ack_epoch += 1
            self._away[guid] = (p, now + self.away_retention_s)
            while len(self._away) > MAX_AWAY_READERS:
                del self._away[next(iter(self._away))]
            self._purge()
            return [self._matched(-1, hex_)]
        if guid in self.proxies or guid in self._incompatible:
            return []
        policy = incompatible_policy(self._offered, mq.as_profile())
        away = self._away.pop(guid, None)
        if away is not None and policy is None:
            return self._resume(away[0], now)
        if policy is not None:
            self._incompatible.add(guid)
            self.incompatible += 1
            return [
                Notify(
                    "incompatible_qos", IncompatibleQosStatus(self.incompatible, 1, policy, hex_)
                )
            ]
        start = (
            self.first if (self.qos.transient_local and mq.transient_local) else self.last_seq + 1
        )
        p = _ReaderProxy(guid, hex_, mq.reliable, start, wire.directed_key(self.topic, hex_))
        p.requested_deadline_s = mq.as_profile().deadline_s
        self.proxies[guid] = p
        self._rearm(self._mono())
        self.n_reliable += p.reliable
        self.ack_epoch += 1
        if p.reliable:
            self.history_offered += max(self.last_seq - start + 1, 0)
        self.matched_total += 1
        return [self._matched(1, hex_), self._sync(p, now)]

    def _resume(self, p: _ReaderProxy, now: float) -> list[Action]:
        """An away reader is back (same guid): its match goes on from what it acknowledged.
        The SYNC repeats its old start (a synced reader ignores it) until it ACKNACKs; its
        NACKs then get what the history still holds and a GAP for the rest."""
        p.synced = False
        p.resent.clear()
        p.resent_frags.clear()
        self.proxies[p.guid] = p
        self._rearm(now)
        self.n_reliable += p.reliable
        self.ack_epoch += 1
        self.matched_total += 1
        self.resumed += 1
        return [self._matched(1, p.hex), self._sync(p, now)]

    def _expire_away(self, now: float) -> None:
        away = self._away
        while away and next(iter(away.values()))[1] <= now:
            del away[next(iter(away))]

    @property
    def has_audience(self) -> bool:
        """A sample written now reaches a reader or is reported lost to one: a reader is
        matched, or away with its match to resume (its retention not checked: cheap, for the
        write path; an expired one is dropped at the next liveliness change or ``tick``)."""
        return bool(self.proxies or self._away)

    @property
    def awaited_count(self) -> int:
        """Readers away whose match may still resume: what is written now will reach them or
        be reported lost to them when they are back, so it is not written to no one."""
        self._expire_away(self.clock.monotonic_s())
        return len(self._away)

    def _matched(self, change: int, peer: str) -> Notify:
        return Notify(
            "matched",
            MatchedStatus(self.matched_total, max(change, 0), len(self.proxies), change, peer),
        )

    # ------------------------------------------------------------------ reliability
    def on_acknack(self, key: str, payload: bytes, attachment: bytes | None) -> list[Action]:
        an = wire.decode_acknack(payload)
        if an is None or an.writer != self.guid:
            self.bad("malformed ACKNACK", key)
            return []
        if not key.endswith(f"/{an.reader.hex()}"):
            # a reader's ACKNACKs go on its own key: another reader's guid there is forged
            self.bad("ACKNACK with another guid than its key's reader", key)
            return []
        p = self.proxies.get(an.reader)
        if p is None:
            self.bad("ACKNACK from an unmatched reader", an.reader.hex(), race=True)
            return []
        now = self.clock.monotonic_s()
        p.synced = True
        base = min(an.base, self.last_seq + 1)
        if base > p.acked:
            p.acked = base
            self.ack_epoch += 1
        if p.resent:
            p.confirmed(max(p.acked, self.first))
        # A seq resent less than the holdoff ago is still on its way (a burst of resends to a
        # reader that just joined takes longer than its NACK repeat): not resent again, so a
        # TRANSIENT_LOCAL history goes out about once per reader, not once per NACK.
        holdoff = now - p.holdoff_s()
        actions: list[Action] = []
        budget = RESEND_BUDGET
        lost_ranges: list[tuple[int, int]] = []
        for lo_, hi_ in an.missing:
            lo, hi = max(lo_, base), min(hi_, self.last_seq)
            if lo < p.start and lo <= hi:
                # before this match's start: a reader resuming a match this writer had
                # forgotten (it was away too long) asks for seqs it will never get
                lost_ranges.append((lo, min(hi, p.start - 1)))
                lo = p.start
            if lo > hi:
                continue
            self.nacks += hi - lo + 1
            self._last_nack_s = now
            self._heartbeat_now_lossy(now)
            if lo < self.first:
                lost_ranges.append((lo, min(hi, self.first - 1)))
                lo = self.first
            seq = lo
            resent = p.resent
            while seq <= hi and budget > 0:
                times = resent.get(seq)
                if times is not None and times[1] > holdoff:
                    self.resends_held_off += 1
                    seq += 1
                    continue
                data, stamp = self.history[seq]
                if len(data) > self.fragment_bytes:  # none of it arrived: every fragment again
                    sent = self._resend_fragments(p, seq, 0, None, an.counter, now, actions)
                    budget -= max(1, sent * RESEND_BUDGET // self._frag_budget)
                else:
                    att = wire.encode_resend(self.guid, seq, stamp, an.counter)
                    actions.append(Send(p.rx_key, data, att))
                    self.retransmitted += 1
                    budget -= 1
                resent[seq] = (times[0] if times is not None else now, now)
                seq += 1
        if an.frags:
            self._answer_fragments(p, an, base, now, actions, lost_ranges)
        if lost_ranges:
            n_lost = sum(hi - lo + 1 for lo, hi in lost_ranges)
            self.gaps += n_lost
            p.lost += n_lost
            self.lost += n_lost
            actions.append(Send(p.rx_key, wire.encode_gap(self.guid, p.guid, lost_ranges)))
            actions.append(Notify("message_lost", MessageLostStatus(self.lost, n_lost, p.hex)))
        self._purge()
        return actions

    def _answer_fragments(
        self,
        p: _ReaderProxy,
        an: wire.AckNack,
        base: int,
        now: float,
        actions: list[Action],
        lost_ranges: list[tuple[int, int]],
    ) -> None:
        """An ACKNACK_FRAG's fragment requests: the fragments still held are resent (up to
        ``FRAGMENT_RESEND_BYTES``), a sample no longer held is GAPed (once per request)."""
        budget = self._frag_budget
        gapped: set[int] = set()
        for seq, lo, hi in an.frags:
            if seq < base or seq > self.last_seq:
                continue  # acknowledged meanwhile, or never written (forged)
            self.fragments_nacked += hi - lo + 1
            self._last_nack_s = now
            self._heartbeat_now_lossy(now)
            if seq < p.start or seq < self.first:
                if seq not in gapped:
                    gapped.add(seq)
                    lost_ranges.append((seq, seq))
                continue
            if budget <= 0:
                continue
            if len(self.history[seq][0]) <= self.fragment_bytes:
                continue  # not sent as fragments: the reader's ACKNACK asks for it whole
            budget -= self._resend_fragments(p, seq, lo, hi, an.counter, now, actions, budget)

    def _resend_fragments(
        self,
        p: _ReaderProxy,
        seq: int,
        first: int,
        last: int | None,
        counter: int,
        now: float,
        actions: list[Action],
        budget: int | None = None,
    ) -> int:
        """Resend fragments ``first .. last`` of ``seq`` to reader ``p`` but those resent to it
        within its holdoff (still on their way); returns how many went."""
        data, stamp = self.history[seq]
        holdoff = now - p.holdoff_s()
        resent = p.resent_frags
        sent = 0
        end = fragment_count(len(data), self.fragment_bytes) - 1
        end = end if last is None else min(last, end)
        for index in range(first, end + 1):
            if budget is not None and sent >= budget:
                break
            at = resent.get((seq, index))
            if at is not None and at > holdoff:
                self.resends_held_off += 1
                continue
            for frag, att in self._fragments(seq, data, stamp, 0, index, index, counter):
                actions.append(Send(p.rx_key, frag, att))
            resent[(seq, index)] = now
            sent += 1
        self.retransmitted += sent
        self.fragments_retransmitted += sent
        return sent

    def tick(self, backlog: int = 0) -> list[Action]:
        now = self.clock.monotonic_s()
        actions: list[Action] = []
        if self.batch:
            due = self.flush_batch(force=False)
            if due is not None:
                actions.append(Send(self.topic, due[0], due[1]))
        if self.qos.lifespan_s > 0:
            self._expire(self.clock.wall_ns())
        if now >= self._next_hb_s:
            self.quiet = False
            if self._heartbeat_due(now):
                # calm: the data carried the heartbeat (every reader answered): the period grows
                # (heartbeat_backoff), and the driver wakes less often
                calm = True
                if self._ack_requested_since_hb and self._data_carries_heartbeat(now):
                    self.heartbeats_piggybacked += 1
                else:
                    calm = False
                    actions.append(self._heartbeat(now, 0))
                if calm:
                    self._grow_heartbeat_period()
                # else the period holds: an unanswered request is a late reader as often as a
                # lost sample, and the heartbeat now sent makes a reader that misses something
                # NACK, which brings the base period back (``_heartbeat_now_lossy``). Falling
                # back on every late answer fed a CEDDP that was behind more heartbeats and
                # ACKNACKs.
                self._next_hb_s = now + self._hb_interval_s
            elif self._link_lossy(now):  # nothing to say, but a sample may soon be lost
                self._grow_heartbeat_period()
                self._next_hb_s = now + self._hb_interval_s
            else:
                self._go_quiet(now)
            self._ack_requested_since_hb = False
            self._ack_on_next_write = True
        for p in self.proxies.values():
            if not p.synced and now - p.last_sync_s >= self.qos.nack_period_s:
                actions.append(self._sync(p, now))
        missed = self._deadline.poll(now)
        if missed:
            actions.append(Notify("deadline", DeadlineMissedStatus(self._deadline.total, missed)))
        if self._lease.poll(now):
            self.liveliness_lost += 1
            actions.append(Notify("liveliness", LivelinessLostStatus(self.liveliness_lost, 1)))
        return actions

    def _heartbeat_now_lossy(self, now: float) -> None:
        """A reader NACKed: the link loses, and a grown heartbeat period is back to its base."""
        base = self.qos.heartbeat_period_s
        if self._hb_interval_s > base:
            self._hb_interval_s = base
            self._next_hb_s = min(self._next_hb_s, now + base)
        self._rearm(now)

    def _grow_heartbeat_period(self) -> None:
        self._hb_interval_s = min(
            2 * self._hb_interval_s, self.qos.heartbeat_backoff * self.qos.heartbeat_period_s
        )

    def _go_quiet(self, now: float) -> None:
        """Nothing to say (every reader synced and acknowledged everything) on a link that lost
        nothing lately: the timer sleeps until a write, a new reader or a NACK re-arms it
        (``_rearm``), or at most ``QUIET_HEARTBEAT_S`` (a liveliness lease's next assertion
        sooner). A writer that wrote now and then woke at every heartbeat period to find
        nothing to say: a robot's report, announce, QoS and config-ack writers 10 times a
        second each, each wake-up a turn of its process's GIL (issue 17).

        A write re-arms the timer without waking the driver: the reader's acknowledgement does
        (the driver then sleeps until the re-armed heartbeat, as before). Waking it for every
        write of a 1 Hz stream cost more wake-ups than the quiet saved. What it costs: when the
        first sample after a quiet spell is lost, nothing acknowledges it and its heartbeat
        comes when the driver next wakes, within ``QUIET_HEARTBEAT_S`` instead of one period;
        the reader's NACK then marks the link lossy, and heartbeats keep their period for
        ``LOSSY_HOLD_PERIODS`` periods."""
        self._grow_heartbeat_period()  # calm, as a period with nothing to say always was
        self.quiet = True
        horizon = now + QUIET_HEARTBEAT_S
        lease = self.qos.lease_duration_s
        if lease > 0:
            horizon = min(horizon, self._last_live_hb_s + lease / 4)
        self._next_hb_s = horizon

    def _rearm(self, now: float) -> None:
        """Out of quiet: the heartbeat timer is due within its period again. The driver sees it
        at its next wake-up (a reader's acknowledgement, a match, a NACK, or its idle period),
        so after a write it can come later than the period: see ``_go_quiet``."""
        if self.quiet:
            self.quiet = False
            self._next_hb_s = min(self._next_hb_s, now + self._hb_interval_s)

    def _data_carries_heartbeat(self, now: float) -> bool:
        """A DATA that asked for an acknowledgement since the timer last fired, and that every
        reader has acknowledged, did a periodic heartbeat's work (RTPS's piggybacked HEARTBEAT):
        every reader is reliable and synced, answered it with an ACKNACK naming what it missed,
        and knows every seq up to that DATA's; automatic liveliness is asserted by any DATA. A
        streaming topic on a clean link then sends no heartbeat messages of its own: at 100 Hz
        they were as many Zenoh messages as the bundled data (issue 17). Not acknowledged yet (the
        DATA or its answer lost, as on a lossy link), the heartbeat goes as before: skipping it
        then raised the p99 staleness of benchmarks/qos_per_topic.py on wifi-bad by a third. What
        it costs: a last sample lost just before a stream stops is announced up to two periods
        after it, not one. A link that loses keeps every heartbeat: from a reader's NACK until
        ``LOSSY_HOLD_PERIODS`` periods without one (a heartbeat also prompts the reader to NACK
        again what it still misses; skipping the acknowledged ones raised the weighted p99
        staleness of qos_per_topic.py on wifi-bad from 66 to 79 ms). Manual liveliness,
        best-effort or unsynced readers and an open batch keep the heartbeat too."""
        if not self.qos.piggyback_heartbeats:
            return False
        if self._manual or self.batch or self._min_acked() <= self._ack_request_seq:
            return False
        if self._link_lossy(now):
            return False
        return all(p.reliable and p.synced for p in self.proxies.values())

    def _link_lossy(self, now: float) -> bool:
        """A reader NACKed within the last ``LOSSY_HOLD_PERIODS`` heartbeat periods."""
        return now - self._last_nack_s < LOSSY_HOLD_PERIODS * self.qos.heartbeat_period_s

    def busy(self) -> bool:
        """A batch waits to go out, or one went out within the batch delay (the topic is
        streaming: the next batch opens any moment, and a driver that went idle in between
        would have to be woken for it), or a reader has not yet confirmed where its match
        starts (SYNC is being repeated): the driver ticks at its fine period."""
        return (
            bool(self.batch)
            or self._mono() - self._last_put_s < self._batch_delay_s
            or any(not p.synced for p in self.proxies.values())
        )

    def _expire(self, wall_ns: int) -> None:
        limit_ns = wall_ns - int(self.qos.lifespan_s * 1e9)
        while self.first <= self.last_seq and self.history[self.first][1] < limit_ns:
            self._drop_front()
            self.lifespan_expired += 1

    def stats(self) -> WriterStats:
        return WriterStats(
            sent=self.last_seq,
            retransmitted=self.retransmitted,
            resends_held_off=self.resends_held_off,
            history_offered=self.history_offered,
            heartbeats_piggybacked=self.heartbeats_piggybacked,
            nacks=self.nacks,
            gaps=self.gaps,
            heartbeats=self.heartbeats,
            lost=self.lost,
            overwritten_unacked=self.overwritten_unacked,
            lifespan_expired=self.lifespan_expired,
            unchanged=self.unchanged,
            deadline_missed=self._deadline.total,
            liveliness_lost=self.liveliness_lost,
            matched=len(self.proxies),
            incompatible=self.incompatible,
            history=len(self.history),
            bad_input=self.bad.total(),
            resumed=self.resumed,
            away=len(self._away),
            fragmented=self.fragmented,
            fragments_sent=self.fragments_sent,
            fragments_retransmitted=self.fragments_retransmitted,
            fragments_nacked=self.fragments_nacked,
        )
