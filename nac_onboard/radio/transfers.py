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
        if self.channel.mac == "802.11" and phy_bps > 0:
            payload_bytes = math.ceil(bits / 8)
            ip_bytes = payload_bytes + TCP_IP_HEADER_BYTES * max(math.ceil(bits / SEGMENT_BITS), 1)
            airtime = 1.0 - self.channel.background_airtime  # what other networks leave of the medium
            seconds = expected_message_s(TIMING, ip_bytes, phy_bps) / airtime
        else:
            seconds = bits / rate_bps
        if loss > 0:
            segments = max(math.ceil(bits / SEGMENT_BITS), 1)
            if self.rng.random() < 1.0 - (1.0 - min(loss, 1.0)) ** segments:
                seconds += RTO_S
        return seconds
