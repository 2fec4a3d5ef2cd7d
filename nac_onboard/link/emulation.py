"""Link emulation by sleeping, the research's method: before a transfer of I bits over a link of rate C the
sender sleeps I/C, where C comes from the radio model at the two vehicles' live distance; below the model's
minimum rate the link is out of range and nothing is sent (DESIGN.md 6).

The links themselves, each pair's radio state and each transfer's time, are nac_onboard.radio.transfers (pure);
this module adds what it cannot have: the simulated clock each look is stamped with, the channel's replay table
read from its file, and the sleeping.

Used by the MPI job (`--emulate sleep`: each send and each answer) and by the agent's throughput probes in SITL
(each probe paced at C). On real vehicles nothing here runs: the radio does it. Times are simulated seconds: at a
speed-up X the sleep lasts I / (C X) on the wall clock (nac_onboard.clock).
"""

from __future__ import annotations

import time
from collections.abc import Hashable

from nac_onboard.clock import Clock
from nac_onboard.radio.channel import ChannelModel
from nac_onboard.radio.files import load_replay
from nac_onboard.radio.transfers import LinkNow, PairLinks


class SleepEmulation:
    def __init__(self, channel: ChannelModel, clock: Clock | None = None, seed: int | None = None):
        self.clock = clock or Clock()
        self.links = PairLinks(channel, seed, load_replay(channel.replay_file) if channel.replay_file else None)

    @property
    def channel(self) -> ChannelModel:
        return self.links.channel

    @property
    def pairs(self) -> dict:
        return self.links.pairs

    def link(self, distance_m: float, pair: Hashable = None, ids: tuple[str, str] | None = None) -> LinkNow:
        """The pair's link now. ids: the two vehicles' ids, for a replay table that recorded them."""
        return self.links.link(self.clock.now_s(), distance_m, pair, ids)

    def transfer_s(self, payload_bits: float, rate_bps: float, loss: float = 0.0, phy_bps: float = 0.0) -> float:
        return self.links.transfer_s(payload_bits, rate_bps, loss, phy_bps)

    def delay(self, payload_bits: float, rate_bps: float, loss: float = 0.0, phy_bps: float = 0.0) -> float:
        """Sleep for the transfer's time, before it happens; returns its simulated seconds."""
        seconds = self.transfer_s(payload_bits, rate_bps, loss, phy_bps)
        self.wait(seconds)
        return seconds

    def wait(self, seconds: float) -> None:
        """Sleep for `seconds` of simulated time (a transfer's, or a queue's ahead of it)."""
        if seconds:
            time.sleep(self.clock.wall_s(seconds))
