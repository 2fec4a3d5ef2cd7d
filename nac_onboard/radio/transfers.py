"""Transfers over emulated links, the pure part of the research's method (DESIGN.md 6): a transfer of I bits
over a link of rate C takes I/C, where C comes from the radio model at the two vehicles' distance; below the
model's minimum rate the link is out of range and nothing is sent.

Each pair (a worker's rank, a probe's peer) has its own radio state (nac_onboard.radio.air_link: shadowing,
fading and rate adaptation), stepped at every look by the simulated time the caller gives since the last one
and by how far the distance changed (the motion this side can see). A transfer that loses a packet (the model's
loss after the MAC's retries) takes a TCP retransmission timeout more, as it would on the kernel network.
No clock and no sleeping here: nac_onboard.link.emulation reads the clock and sleeps these times.
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np

from nac_onboard.radio.air_link import Radio
from nac_onboard.radio.channel import ChannelModel
from nac_onboard.radio.medium import MacTiming, expected_message_s
from nac_onboard.radio.replay import ReplayLinks

SEGMENT_BITS = 1448 * 8  # a TCP segment's payload on a 1500-byte path
TCP_IP_HEADER_BYTES = 52  # IPv4 20 + TCP 20 + the timestamps option 12, per segment
TIMING = MacTiming()
RTO_S = 0.2  # Linux's minimum retransmission timeout: what one lost segment costs a small transfer
MTU_BYTES = 1500
# A loss-based TCP flow (Reno, CUBIC) through a drop-tail FIFO far deeper than its bandwidth-delay product keeps the
# FIFO between about half full (its window halved at a loss) and full: a sawtooth whose time average is 3/4 of the
# buffer (Appenzeller, Keslassy, McKeown, "Sizing Router Buffers", SIGCOMM 2004, section 2: a single flow's queue).
# The frame-level air's records agree: a median 764 of 1,000 packets at paper-flight-static's master (docs/radio.md).
LOSS_BASED_BACKLOG_SHARE = 0.75


@dataclass(frozen=True)
class LinkNow:
    """One link at one moment: the model's rate at the distance, its loss, and whether a transfer can happen."""

    distance_m: float
    capacity_bps: float
    in_range: bool
    loss: float = 0.0
    phy_bps: float = 0.0  # the PHY rate, for a channel whose mac is "802.11" (0 out of range)


class _Pair:
    def __init__(self, channel: ChannelModel, seed: int):
        self.radio = Radio(channel, 1, seed)
        self.t_s: float | None = None
        self.distance_m = 0.0


class PairLinks:
    """The links of one side's pairs, each with its own radio state (seeded from `seed`, the channel's by
    default); `replay`: recorded pairs whose measured rates replace the model's."""

    def __init__(self, channel: ChannelModel, seed: int | None = None, replay: ReplayLinks | None = None):
        self.channel = channel
        self.seed = channel.seed if seed is None else seed
        self.rng = np.random.default_rng(self.seed + 7919)
        self.pairs: dict[Hashable, _Pair] = {}
        self.replay = replay

    def link(self, now_s: float, distance_m: float, pair: Hashable = None,
             ids: tuple[str, str] | None = None) -> LinkNow:
        """The pair's link at simulated time now_s. ids: the two vehicles' ids, for a replay table that
        recorded them."""
        if self.replay is not None and ids is not None:
            recorded = self.replay.rate_bps(ids[0], ids[1], now_s)
            if recorded is not None:
                through = self.channel.usable(recorded)
                return LinkNow(distance_m, recorded if through else 0.0, through, 0.0 if through else 1.0)
        state = self.pairs.get(pair)
        if state is None:
            state = self.pairs[pair] = _Pair(self.channel, self.seed + len(self.pairs))
        dt_s = 0.0 if state.t_s is None else max(now_s - state.t_s, 0.0)
        moved_m = abs(distance_m - state.distance_m) if state.t_s is not None else 0.0
        sample = state.radio.step(dt_s, [distance_m], moved_m=[moved_m],
                                  speed_mps=[moved_m / dt_s if dt_s > 0 else 0.0])
        state.t_s, state.distance_m = now_s, distance_m
        in_range = bool(sample.in_range[0])
        return LinkNow(distance_m, float(sample.goodput_bps[0]), in_range, float(sample.loss[0]),
                       float(sample.phy_bps[0]) if in_range else 0.0)

    def transfer_s(self, payload_bits: float, rate_bps: float, loss: float = 0.0, phy_bps: float = 0.0) -> float:
        """How long a transfer of payload_bits takes at rate_bps (0 when no rate is emulated), a retransmission
        timeout more when one of its segments is lost (loss: the link's, from `link`). With a channel whose mac is
        "802.11" and the link's PHY rate given, the frame-level medium's air time for the message instead: its TCP
        segments aggregated, each exchange paying access, preamble and block ack, as the delay line charges them
        (a lost subframe's retries are in `loss`'s timeout, as they are when the delay line drops it)."""
        if rate_bps <= 0:
            return 0.0
        bits = payload_bits + self.channel.overhead_bits
        ip_bytes = math.ceil(bits / 8) + TCP_IP_HEADER_BYTES * max(math.ceil(bits / SEGMENT_BITS), 1)
        seconds = _sent_s(self.channel, ip_bytes, bits, rate_bps, phy_bps)
        if loss > 0:
            segments = max(math.ceil(bits / SEGMENT_BITS), 1)
            if self.rng.random() < 1.0 - (1.0 - min(loss, 1.0)) ** segments:
                seconds += RTO_S
        return seconds


def probe_backlog_packets(queue_packets: int, probe_duration_s: float, probe_period_s: float,
                          congestion_control: str) -> float:
    """The mean of what the probes alongside the job keep in the probing station's transmit queue, in packets: a
    loss-based flow's standing backlog (LOSS_BASED_BACKLOG_SHARE of the queue) for the share of the time the probes
    run. 0 for BBR and the host's default, whose flows keep a queue of about their bandwidth-delay product (a few
    packets here). Not modelled: a probe's slow start, which fills the queue at the link's rate (a slow link's
    2 s probe puts fewer packets in it than this)."""
    if congestion_control not in ("reno", "cubic"):
        return 0.0
    duty = min(probe_duration_s / probe_period_s, 1.0) if probe_period_s > 0 else 0.0
    return LOSS_BASED_BACKLOG_SHARE * queue_packets * duty


def backlog_drain_s(channel: ChannelModel, backlog_packets: float, links: list[LinkNow]) -> float:
    """How long a message entering a transmit queue waits for the backlog ahead of it (simulated seconds): packets
    of the MTU, shared equally among the links in range (flows through one FIFO see one queue's delay, so
    equal round trips and, for Reno, equal windows; probed in turn, the same on average), each share sent as
    transfer_s sends a message over its link (the medium's aggregated exchanges for an 802.11 channel, else
    bits / capacity). A flow to a link out of range keeps almost nothing queued (its TCP backs off)."""
    through = [link for link in links if link.in_range and link.capacity_bps > 0]
    if backlog_packets <= 0 or not through:
        return 0.0
    share_bytes = backlog_packets * MTU_BYTES / len(through)
    return sum(_sent_s(channel, math.ceil(share_bytes), share_bytes * 8, link.capacity_bps, link.phy_bps)
               for link in through)


def _sent_s(channel: ChannelModel, ip_bytes: int, bits: float, rate_bps: float, phy_bps: float) -> float:
    """How long a message takes over a link: with a channel whose mac is "802.11" and the link's PHY rate, the
    medium's time for its ip_bytes (expected_message_s) in what other networks leave of the air; else its bits at
    the link's rate."""
    if channel.mac == "802.11" and phy_bps > 0:
        return expected_message_s(TIMING, ip_bytes, phy_bps) / (1.0 - channel.background_airtime)
    return bits / rate_bps
