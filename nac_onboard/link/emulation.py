"""Link emulation by distance, the research's method: before a transfer of I bits over a link of capacity C the
sender sleeps I/C, where C comes from the channel model at the two vehicles' live distance; below the model's
minimum rate the link is out of range and nothing is sent (DESIGN.md 6).

Used by the MPI job (`--emulate sleep`: each send and each answer) and by the agent's throughput probes in SITL
(each probe paced at C). On real vehicles nothing here runs: the radio does it. Times are simulated seconds: at a
speed-up X the sleep lasts I / (C X) on the wall clock (nac_onboard.clock).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from nac_onboard.clock import Clock
from nac_onboard.link.channel import ChannelModel


@dataclass(frozen=True)
class LinkNow:
    """One link at one moment: the model's capacity at the distance, and whether a transfer can happen."""

    distance_m: float
    capacity_bps: float
    in_range: bool


class SleepEmulation:
    def __init__(self, channel: ChannelModel, clock: Clock | None = None):
        self.channel = channel
        self.clock = clock or Clock()

    def link(self, distance_m: float) -> LinkNow:
        capacity = self.channel.capacity_bps(distance_m)
        return LinkNow(distance_m, capacity, self.channel.usable(capacity))

    def transfer_s(self, payload_bits: float, rate_bps: float) -> float:
        """How long a transfer of payload_bits takes at rate_bps (0 when no rate is emulated)."""
        return (payload_bits + self.channel.overhead_bits) / rate_bps if rate_bps > 0 else 0.0

    def delay(self, payload_bits: float, rate_bps: float) -> float:
        """Sleep for the transfer's time, before it happens; returns its simulated seconds."""
        seconds = self.transfer_s(payload_bits, rate_bps)
        if seconds:
            time.sleep(self.clock.wall_s(seconds))
        return seconds
