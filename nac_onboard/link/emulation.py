"""Link emulation by sleeping, the research's method: before a transfer of I bits over a link of rate C the
sender sleeps I/C, where C comes from the radio model at the two vehicles' live distance; below the model's
minimum rate the link is out of range and nothing is sent (DESIGN.md 6).

Each pair (a worker's rank, a probe's peer) has its own radio state (nac_onboard.link.radio: shadowing, fading
and rate adaptation), stepped at every look by the simulated time since the last one and by how far the
distance changed (the motion this side can see). A transfer that loses a packet (the model's loss after the
MAC's retries) waits a TCP retransmission timeout more, as it would on the kernel network.

Used by the MPI job (`--emulate sleep`: each send and each answer) and by the agent's throughput probes in SITL
(each probe paced at C). On real vehicles nothing here runs: the radio does it. Times are simulated seconds: at a
speed-up X the sleep lasts I / (C X) on the wall clock (nac_onboard.clock).
"""

from __future__ import annotations

import math
import time
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np

from nac_onboard.clock import Clock
from nac_onboard.link.channel import ChannelModel
from nac_onboard.link.radio import Radio
from nac_onboard.link.replay import ReplayLinks

SEGMENT_BITS = 1448 * 8  # a TCP segment's payload on a 1500-byte path
RTO_S = 0.2  # Linux's minimum retransmission timeout: what one lost segment costs a small transfer


@dataclass(frozen=True)
class LinkNow:
    """One link at one moment: the model's rate at the distance, its loss, and whether a transfer can happen."""

    distance_m: float
    capacity_bps: float
    in_range: bool
    loss: float = 0.0


class _Pair:
    def __init__(self, channel: ChannelModel, seed: int):
        self.radio = Radio(channel, 1, seed)
        self.t_s: float | None = None
        self.distance_m = 0.0


class SleepEmulation:
    def __init__(self, channel: ChannelModel, clock: Clock | None = None, seed: int | None = None):
        self.channel = channel
        self.clock = clock or Clock()
        self.seed = channel.seed if seed is None else seed
        self.rng = np.random.default_rng(self.seed + 7919)
        self.pairs: dict[Hashable, _Pair] = {}
        self.replay = ReplayLinks.load(channel.replay_file) if channel.replay_file else None

    def link(self, distance_m: float, pair: Hashable = None, ids: tuple[str, str] | None = None) -> LinkNow:
        """The pair's link now. ids: the two vehicles' ids, for a replay table that recorded them."""
        if self.replay is not None and ids is not None:
            recorded = self.replay.rate_bps(ids[0], ids[1], self.clock.now_s())
            if recorded is not None:
                through = self.channel.usable(recorded)
                return LinkNow(distance_m, recorded if through else 0.0, through, 0.0 if through else 1.0)
        state = self.pairs.get(pair)
        if state is None:
            state = self.pairs[pair] = _Pair(self.channel, self.seed + len(self.pairs))
        now_s = self.clock.now_s()
        dt_s = 0.0 if state.t_s is None else max(now_s - state.t_s, 0.0)
        moved_m = abs(distance_m - state.distance_m) if state.t_s is not None else 0.0
        sample = state.radio.step(dt_s, [distance_m], moved_m=[moved_m],
                                  speed_mps=[moved_m / dt_s if dt_s > 0 else 0.0])
        state.t_s, state.distance_m = now_s, distance_m
        return LinkNow(distance_m, float(sample.goodput_bps[0]), bool(sample.in_range[0]), float(sample.loss[0]))

    def transfer_s(self, payload_bits: float, rate_bps: float, loss: float = 0.0) -> float:
        """How long a transfer of payload_bits takes at rate_bps (0 when no rate is emulated), a retransmission
        timeout more when one of its segments is lost (loss: the link's, from `link`)."""
        if rate_bps <= 0:
            return 0.0
        bits = payload_bits + self.channel.overhead_bits
        seconds = bits / rate_bps
        if loss > 0:
            segments = max(math.ceil(bits / SEGMENT_BITS), 1)
            if self.rng.random() < 1.0 - (1.0 - min(loss, 1.0)) ** segments:
                seconds += RTO_S
        return seconds

    def delay(self, payload_bits: float, rate_bps: float, loss: float = 0.0) -> float:
        """Sleep for the transfer's time, before it happens; returns its simulated seconds."""
        seconds = self.transfer_s(payload_bits, rate_bps, loss)
        if seconds:
            time.sleep(self.clock.wall_s(seconds))
        return seconds
