"""The shared Wi-Fi medium, frame by frame (pure, seeded; issue 28): every station's transmit queue, first in first
out and bounded as its driver's is, and the 802.11 distributed coordination function that gives the air to one
station at a time. What a frame costs is the standard's timing, not a fitted efficiency: the wait for the medium
(AIFS and a random backoff of slots, doubling after a failed exchange), the HT preamble, the data at the pair's PHY
rate, SIFS and the block acknowledgement at the control rate; frames to one receiver are aggregated (A-MPDU) as
Linux's drivers do; each subframe is lost with the pair's frame error rate and retried until the retry limit
(the first half at the chosen rate, the rest at the fallback rate, as a Minstrel retry chain ends); two stations
whose backoffs end in the same slot collide and both pay for it. A small message therefore costs a few hundred
microseconds on an idle medium and waits behind whatever its station queued before it.

Time is the caller's (simulated seconds): offer() what a station sends, run_until() the medium to a time, and read
the deliveries (with their queue wait and air time) that have completed by then.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

BROADCAST = -1


@dataclass(frozen=True)
class MacTiming:
    """802.11n in the 2.4 GHz band, 20 MHz, one spatial stream, long guard interval, best-effort traffic."""

    slot_s: float = 9e-6  # IEEE Std 802.11-2016, HT PHY characteristics: aSlotTime, short slot (2.4 GHz, all HT)
    sifs_s: float = 10e-6  # same table: aSIFSTime in 2.4 GHz
    signal_extension_s: float = 6e-6  # same table: aSignalExtension, after every OFDM PPDU in 2.4 GHz
    aifsn: int = 3  # the default EDCA parameter set, AC_BE (best effort: all of NAC's traffic)
    cw_min: int = 15  # AC_BE CWmin = aCWmin (15 for the OFDM and HT PHYs)
    cw_max: int = 1023  # AC_BE CWmax = aCWmax
    ht_preamble_s: float = 36e-6  # HT-mixed PPDU: L-STF 8 + L-LTF 8 + L-SIG 4 + HT-SIG 8 + HT-STF 4 + one HT-LTF 4 us
    legacy_preamble_s: float = 20e-6  # OFDM PPDU (the block ack): preamble 16 us + SIGNAL 4 us
    symbol_s: float = 4e-6  # OFDM symbol with the 800 ns guard interval
    control_rate_bps: float = 24e6  # a control response goes at a basic rate: 24 Mbit/s, the highest mandatory one
    broadcast_rate_bps: float = 1e6  # group frames at the lowest basic rate (mac80211's default for 2.4 GHz)
    block_ack_bytes: int = 32  # compressed BlockAck frame
    mpdu_overhead_bytes: int = 38  # QoS data MAC header 26 + FCS 4 + LLC/SNAP 8 (RFC 1042), per IP packet
    delimiter_bytes: int = 4  # A-MPDU subframe delimiter; subframes are padded to 4 bytes
    max_ampdu_bytes: int = 65535  # HT capability "maximum A-MPDU length exponent" 3: 2^16 - 1 bytes
    max_ampdu_frames: int = 64  # the block ack window
    max_ppdu_s: float = 4e-3  # Linux ath9k: an aggregate holds at most 4 ms of airtime (ath_max_4ms_framelen)

    @property
    def aifs_s(self) -> float:
        return self.sifs_s + self.aifsn * self.slot_s

    def ppdu_s(self, payload_bytes: int, rate_bps: float, preamble_s: float | None = None) -> float:
        """Airtime of one PPDU: preamble, SERVICE (16 bits), the payload and the tail (6 bits) in whole symbols."""
        bits_per_symbol = rate_bps * self.symbol_s
        symbols = math.ceil((16 + 8 * payload_bytes + 6) / bits_per_symbol)
        preamble = self.ht_preamble_s if preamble_s is None else preamble_s
        return preamble + symbols * self.symbol_s + self.signal_extension_s

    def block_ack_s(self) -> float:
        return self.ppdu_s(self.block_ack_bytes, self.control_rate_bps, self.legacy_preamble_s)

    def subframe_bytes(self, ip_bytes: int) -> int:
        raw = ip_bytes + self.mpdu_overhead_bytes + self.delimiter_bytes
        return raw + (-raw) % 4


# Linux's default transmit queue: DEFAULT_TX_QUEUE_LEN, the pfifo_fast a companion's wlan0 gets, in packets.
DEFAULT_QUEUE_PACKETS = 1000
# Retransmissions before a frame is lost to IP: 802.11's dot11ShortRetryLimit, 7 by default, an integer of 1..255
# in its MIB (IEEE 802.11-2016, Annex C), of which 0 here means a single try.
DEFAULT_RETRY_LIMIT = 7
MAX_RETRY_LIMIT = 255


@dataclass(slots=True)
class Frame:
    """What a station queued: one IP packet, or a TCP segmentation offload's run of them (`segments` packets of
    one flow handed over as one, as Linux hands them to a TUN device): on the air each segment is its own MPDU."""

    src: int
    dst: int  # a station, or BROADCAST
    size_bytes: int  # the IP packet, or the segments' bytes together
    item: object  # the caller's (the packet itself, for a delay line)
    enqueued_s: float
    segments: int = 1
    first_sent_s: float | None = None
    queued: int | None = None  # how many of the run's segments found room in the queue (None: all)
    tries: list[int] = field(init=False)  # per segment still to send: failed tries so far
    pending: list[int] = field(init=False)  # those segments' places in the run, in step with tries
    lost: list[int] = field(init=False)  # places of the segments dropped at the queue or failed every try

    def __post_init__(self):
        self.queued = self.segments if self.queued is None else self.queued
        self.tries = [0] * self.queued
        self.pending = list(range(self.queued))
        self.lost = list(range(self.queued, self.segments))  # the tail a full queue had no room for

    @property
    def segment_bytes(self) -> int:
        return -(-self.size_bytes // self.segments)


class Delivery(NamedTuple):  # a tuple: built for every frame, where a frozen dataclass costs a microsecond more
    frame: Frame
    dst: int
    delivered_s: float
    lost_segments: tuple[int, ...] = ()  # a run's segments that failed every try (the rest got through)

    @property
    def queue_s(self) -> float:
        """From the queue to the air: waiting behind earlier frames, and for the medium."""
        return self.frame.first_sent_s - self.frame.enqueued_s


@dataclass
class MediumStats:
    offered: int = 0
    delivered: int = 0
    segments_delivered: int = 0  # packets delivered, an offload run counted as the packets it stands for
    queue_drops: int = 0  # packets dropped at a full queue (a run's segments each count)
    retry_drops: int = 0  # packets that failed every try (a run's segments each count)
    exchanges: int = 0
    collisions: int = 0
    busy_s: float = 0.0  # airtime used, collisions and acknowledgements included
    airtime_s: dict = field(default_factory=dict)  # station -> airtime its transmissions used


class Medium:
    """One collision domain: every station hears every other (the vehicles fly within tens of metres)."""

    def __init__(self, stations: int, timing: MacTiming = MacTiming(), queue_packets: int = DEFAULT_QUEUE_PACKETS,
                 retry_limit: int = DEFAULT_RETRY_LIMIT, seed: int = 0):
        if queue_packets < 1:
            raise ValueError(f"queue_packets must be >= 1, got {queue_packets}")
        if not 0 <= retry_limit <= MAX_RETRY_LIMIT:
            raise ValueError(f"retry_limit must be in 0..{MAX_RETRY_LIMIT}, got {retry_limit}")
        self.n, self.timing, self.queue_packets, self.retry_limit = stations, timing, queue_packets, retry_limit
        self.rng = np.random.default_rng(seed)
        self.queues: list[deque[Frame]] = [deque() for _ in range(stations)]
        self.queued = [0] * stations  # packets in each queue
        self.cw = [timing.cw_min] * stations
        self.backoff: list[int | None] = [None] * stations  # slots left to count, while backlogged
        self.counting_from_s = [0.0] * stations  # when its count (re)started: backlogged or medium idle again
        self.idle_from_s = 0.0  # the medium is free from here on
        self.phy_bps = np.zeros((stations, stations))
        self.per = np.ones((stations, stations))
        self.fallback_bps = np.zeros((stations, stations))
        self.fallback_per = np.ones((stations, stations))
        self.stats = MediumStats(airtime_s={i: 0.0 for i in range(stations)})
        self._done: list[Delivery] = []  # delivered by the last transmission run, not yet handed out
        self._start: tuple[float, list[int], int] | None | bool = False  # _next_start's answer (False: not known)
        # the timing's sums once, and the links as lists: a frame's work at 4x must fit in some 40 us of wall time
        self._slot_s, self._aifs_s = timing.slot_s, timing.aifs_s
        self._sifs_s, self._block_ack_s = timing.sifs_s, timing.block_ack_s()
        self._links: tuple[list, list, list, list] = ([], [], [], [])
        self._ppdu_bytes: dict[float, int] = {}  # rate -> _ppdu_bytes_within's answer

    def set_links(self, phy_bps, per, fallback_bps=None, fallback_per=None) -> None:
        """Each ordered pair's PHY rate (0: out of range) and frame error rate; the retry chain's fallback (MCS 0)."""
        self.phy_bps, self.per = np.asarray(phy_bps, float), np.clip(np.asarray(per, float), 0.0, 1.0)
        self.fallback_bps = self.phy_bps if fallback_bps is None else np.asarray(fallback_bps, float)
        self.fallback_per = self.per if fallback_per is None else np.clip(np.asarray(fallback_per, float), 0.0, 1.0)
        self._links = (self.phy_bps.tolist(), self.per.tolist(), self.fallback_bps.tolist(),
                       self.fallback_per.tolist())

    def offer(self, t_s: float, src: int, dst: int, size_bytes: int, item: object = None, segments: int = 1) -> bool:
        """Queue a packet (or a run of `segments` packets) at station src, in time order after run_until(t_s);
        False: its queue had no room for it. A queue holds queue_packets packets and drops what does not fit, packet
        by packet, as a FIFO of the MTU's packets does: a run takes the room there is, its tail is dropped (and
        delivered as lost segments), so how the sender's stack batched its packets, which a speed-up changes, does
        not decide what is dropped."""
        self.stats.offered += 1
        segments = max(segments, 1)
        room = min(self.queue_packets - self.queued[src], segments)
        self.stats.queue_drops += segments - room
        if room == 0:
            return False
        self.queues[src].append(Frame(src, dst, size_bytes, item, t_s, segments, queued=room))
        self.queued[src] += room
        self._start = False
        if self.backoff[src] is None:
            self.backoff[src] = int(self.rng.integers(0, self.cw[src] + 1))
            self.counting_from_s[src] = max(t_s, self.idle_from_s)
        return True

    def flush(self, station: int) -> int:
        """The station's queue emptied (its radio lost its power): the packets it held, gone with it. What it had on
        the air already is delivered as the air decided."""
        dropped = self.queued[station]
        self.queues[station].clear()
        self.queued[station] = 0
        self.backoff[station], self.cw[station] = None, self.timing.cw_min
        self._start = False
        return dropped

    def backlog(self, station: int) -> int:
        """Packets queued at the station (a segmentation offload's run counts each of its segments)."""
        return self.queued[station]

    def next_event_s(self) -> float | None:
        """When the next transmission starts or the next delivery completes (None: nothing is under way)."""
        start = self._next_start()
        times = [start[0]] if start is not None else []
        times += [d.delivered_s for d in self._done]
        return min(times) if times else None

    def run_until(self, t_s: float, start_horizon_s: float = 0.0) -> list[Delivery]:
        """Every transmission that starts by t_s (or t_s + start_horizon_s: decided that much ahead, so a caller
        on a real clock need not wake for each start), done; the deliveries completed by t_s, in time order."""
        while (start := self._next_start()) is not None and start[0] <= t_s + start_horizon_s:
            self._transmit(*start)
        if not self._done:
            return []
        ready = [d for d in self._done if d.delivered_s <= t_s]
        if ready:
            self._done = [d for d in self._done if d.delivered_s > t_s]
            ready.sort(key=_delivered_s)
        return ready

    # ---- one channel access ----------------------------------------------------------------------------------
    def _slots_before_counting(self, station: int) -> int:
        """Slots after the idle medium's AIFS that passed before the station began counting (it became backlogged
        during them)."""
        base = self.idle_from_s + self._aifs_s
        return max(0, math.ceil((self.counting_from_s[station] - base) / self._slot_s - 1e-9))

    def _slot_of(self, station: int) -> int:
        """The slot (counted from the end of AIFS after the medium went idle) in which the station's count ends."""
        return self._slots_before_counting(station) + self.backoff[station]

    def _next_start(self) -> tuple[float, list[int], int] | None:
        """When the next transmission starts, who sends, in which slot. Kept until a packet is offered or a
        transmission is made, the only changes to what it depends on: a delay line asks several times a frame, and
        at 4x a frame's whole hold is some 40 us of wall time."""
        if self._start is False:
            self._start = self._find_next_start()
        return self._start

    def _find_next_start(self) -> tuple[float, list[int], int] | None:
        first, winners = None, []
        for i, queue in enumerate(self.queues):
            if queue:
                slot = self._slot_of(i)
                if first is None or slot < first:
                    first, winners = slot, [i]
                elif slot == first:
                    winners.append(i)
        if first is None:
            return None
        return self.idle_from_s + self._aifs_s + first * self._slot_s, winners, first

    def _transmit(self, start_s: float, winners: list[int], slot: int) -> None:
        self._start = False
        for i in range(self.n):  # the losers froze their count where the medium went busy
            if self.queues[i] and i not in winners:
                counted = max(slot - self._slots_before_counting(i), 0)
                self.backoff[i] = max(self.backoff[i] - counted, 0)
        ends = []
        for src in winners:
            ends.append(self._exchange(src, start_s, collided=len(winners) > 1))
        self.stats.exchanges += 1
        self.stats.collisions += len(winners) > 1
        self.idle_from_s = max(ends)
        self.stats.busy_s += self.idle_from_s - start_s
        for i in range(self.n):
            if not self.queues[i]:
                self.backoff[i] = None
                continue
            if i in winners:  # a new count for its next frame, from a window reset or doubled by the outcome
                self.backoff[i] = int(self.rng.integers(0, self.cw[i] + 1))
            self.counting_from_s[i] = self.idle_from_s

    def _ppdu_bytes_within(self, rate_bps: float) -> int:
        """The most bytes a PPDU at this rate carries within the timing's max_ppdu_s (ppdu_s grows with the bytes)."""
        most = self._ppdu_bytes.get(rate_bps)
        if most is None:
            t = self.timing
            symbols = (t.max_ppdu_s - t.ht_preamble_s - t.signal_extension_s) / t.symbol_s
            most = max(int((symbols * rate_bps * t.symbol_s - 22) // 8), 0)  # near it; then exactly, by ppdu_s
            while most > 0 and t.ppdu_s(most, rate_bps) > t.max_ppdu_s:
                most -= 1
            while t.ppdu_s(most + 1, rate_bps) <= t.max_ppdu_s:
                most += 1
            self._ppdu_bytes[rate_bps] = most
        return most

    def _exchange(self, src: int, start_s: float, collided: bool) -> float:
        """src sends its head frames (an aggregate to one receiver, or one broadcast); returns when the medium is
        free again. A collision loses every subframe."""
        t = self.timing
        queue = self.queues[src]
        head = queue[0]
        if head.dst == BROADCAST:
            queue.popleft()
            self.queued[src] -= head.queued
            head.first_sent_s = start_s if head.first_sent_s is None else head.first_sent_s
            end = start_s + t.ppdu_s(t.subframe_bytes(head.size_bytes), t.broadcast_rate_bps, t.legacy_preamble_s)
            if not collided:
                for j in range(self.n):
                    # at the group rate, as robust as the slowest modelled rate at least: MCS 0's error rate, not
                    # the pair's data rate's (a broadcast has no retries to make up for a fast rate's losses)
                    if j != src and self.phy_bps[src, j] > 0 and self.rng.random() >= self.fallback_per[src, j]:
                        self._done.append(Delivery(head, j, end))
                        self.stats.delivered += 1
                        self.stats.segments_delivered += 1
            self.stats.airtime_s[src] += end - start_s
            return end
        dst = head.dst
        phy_bps, per_of, fallback_bps, fallback_per = self._links
        fallback = max(head.tries) >= (self.retry_limit + 1) // 2
        rate = (fallback_bps if fallback else phy_bps)[src][dst]
        per = (fallback_per if fallback else per_of)[src][dst]
        if rate <= 0:  # out of range: the tries go at the lowest rate and all fail
            rate, per = t.control_rate_bps, 1.0
        batch, count, size = [], 0, 0  # (frame, how many of its segments) in this aggregate
        # after the first subframe, one more fits while the aggregate stays within both byte limits
        max_frames, max_bytes = t.max_ampdu_frames, t.max_ampdu_bytes
        cap = min(max_bytes, self._ppdu_bytes_within(rate))
        for frame in queue:
            if frame.dst != dst:
                break
            sub = t.subframe_bytes(frame.segment_bytes)
            fit, left = 0, len(frame.tries)
            if count == 0 and left and sub <= max_bytes:
                fit, count, size = 1, 1, sub
            more = min(left - fit, max_frames - count, max((cap - size) // sub, 0))
            fit, count, size = fit + more, count + more, size + more * sub
            if fit:
                batch.append((frame, fit))
            if fit < left:
                break
        data_end = start_s + t.ppdu_s(size, rate)
        end = data_end + self._sifs_s + self._block_ack_s
        self.stats.airtime_s[src] += end - start_s
        through = 0
        for frame, sent in batch:
            frame.first_sent_s = start_s if frame.first_sent_s is None else frame.first_sent_s
            tries, places = frame.tries, frame.pending
            if collided:
                failed = [True] * sent
            else:  # one draw a subframe sent, in order: rng.random(n) is n calls of rng.random()
                failed = [self.rng.random() < per] if sent == 1 else (self.rng.random(sent) < per).tolist()
            kept, pending = [], []
            for k in range(sent):
                if not failed[k]:
                    through += 1
                elif tries[k] + 1 > self.retry_limit:
                    frame.lost.append(places[k])
                else:
                    kept.append(tries[k] + 1)
                    pending.append(places[k])
            frame.tries, frame.pending = kept + tries[sent:], pending + places[sent:]
        # in the queue's order, as the receiver's reorder buffer releases them: a frame through (or lost) behind
        # one still being retried waits for it
        while queue and queue[0].dst == dst and not queue[0].tries:
            frame = queue.popleft()
            self.queued[src] -= frame.queued
            # what failed every try is lost, each MPDU on its own: of a run, only those segments
            self.stats.retry_drops += len(frame.lost) - (frame.segments - frame.queued)
            if len(frame.lost) < frame.segments:
                self._done.append(Delivery(frame, dst, data_end, tuple(sorted(frame.lost))))
                self.stats.delivered += 1
                self.stats.segments_delivered += frame.segments - len(frame.lost)
        # no block ack came back (nothing got through): the window doubles; any acknowledgement resets it
        self.cw[src] = t.cw_min if through else min(2 * self.cw[src] + 1, t.cw_max)
        return end


def _delivered_s(delivery: Delivery) -> float:
    return delivery.delivered_s


def expected_message_s(timing: MacTiming, message_bytes: int, phy_bps: float, per: float = 0.0,
                       mtu_bytes: int = 1500) -> float:
    """The mean time from a message's arrival at a medium idle for at least AIFS to its last data received, as the
    medium charges it (the sleep network's per-message charge): IP packets of the MTU, aggregated as the medium
    does. The first exchange waits for the next slot boundary (half a slot on average) and the mean backoff (half
    the minimum window), then its preamble and data; each further one also waits for the last one's SIFS and block
    ack and AIFS. Lost subframes are sent again (1 / (1 - per) times the air time on average)."""
    if phy_bps <= 0 or per >= 1:
        return math.inf
    packets = [mtu_bytes] * (message_bytes // mtu_bytes) + ([message_bytes % mtu_bytes] if message_bytes % mtu_bytes
                                                            else [])
    sizes, batch, size = [], 0, 0
    for packet in packets or [0]:
        sub = timing.subframe_bytes(packet)
        if batch and (batch >= timing.max_ampdu_frames or size + sub > timing.max_ampdu_bytes
                      or timing.ppdu_s(size + sub, phy_bps) > timing.max_ppdu_s):
            sizes.append(size)
            batch, size = 0, 0
        batch += 1
        size += sub
    sizes.append(size)
    backoff_s = timing.cw_min / 2 * timing.slot_s
    between_s = timing.sifs_s + timing.block_ack_s() + timing.aifs_s  # the last exchange's ack, then AIFS
    total = timing.slot_s / 2 + len(sizes) * backoff_s + (len(sizes) - 1) * between_s
    total += sum(timing.ppdu_s(s, phy_bps) for s in sizes)
    return total / (1.0 - per)


def expected_echo_s(timing: MacTiming, message_bytes: int, phy_bps: float) -> float:
    """The mean round trip of an echo whose reply is sent the moment the request is received (a host's stack
    answering), on a medium idle before the request: the request as expected_message_s; the reply finds the medium
    busy with the request's block ack, so it waits for that and AIFS (not for a slot boundary), then its backoff
    and PPDU. Error-free links."""
    one_way_s = expected_message_s(timing, message_bytes, phy_bps)
    return 2 * one_way_s + timing.sifs_s + timing.block_ack_s() + timing.aifs_s - timing.slot_s / 2


@functools.lru_cache(maxsize=4096)
def saturated_goodput_bps(phy_bps: float, timing: MacTiming = MacTiming(), mtu_bytes: int = 1500) -> float:
    """What a long transfer of IP packets gets from a PHY rate on an idle medium, every cost of the medium paid:
    the 802.11 counterpart of PHY rate x MAC efficiency (about 0.92 of 65 Mbit/s, 0.84 of 6.5)."""
    if phy_bps <= 0:
        return 0.0
    message = 200 * mtu_bytes
    # back to back, each message also holds the medium for its last ack and the AIFS before the next, and starts
    # on a slot boundary the last one's AIFS ended on
    each_s = expected_message_s(timing, message, phy_bps, 0.0, mtu_bytes) - timing.slot_s / 2 \
        + timing.sifs_s + timing.block_ack_s() + timing.aifs_s
    return 8 * message / each_s
