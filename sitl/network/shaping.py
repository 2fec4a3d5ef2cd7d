"""What the air between the vehicles does this instant, and the tc/nft text that makes a kernel network do it
(pure: positions in, numbers and command lines out; sitl.network.shaper applies them).

Layout (sitl.network.air builds it): every companion namespace has one interface, `air0`, on a bridge in an
`air` namespace. Traffic from station i to station j leaves the bridge through j's port, where an HTB class per
source (i -> j) holds the pair's rate; nftables in the bridge drops the pair's loss. With a shared medium the
access point (the master, as in the research's testbed) relays what one station sends another (the pair is shaped
as its two hops through it: `through_the_ap`), and spends one airtime budget on everything it receives (a
parent class over its port's pair classes) and on everything it sends (the same on its own `air0`): concurrent
transfers through it split the budget, each guaranteed an equal part and borrowing what the others leave.
Probe traffic from the access point to a station's throughput port has its own class at the pair's rate,
outside the budget: a probe then measures the link, not what the MPI job leaves of it (the research measured
throughput in flights of its own).

Rates and losses are the radio model's (nac_onboard.radio.air_link: path loss, shadowing, fading, the 802.11n rate
and the packets its errors cost), times the speed-up on the wire (time dilation: a transfer of B bits at rate C
lasts B / C simulated seconds at any speed-up). Out of range: every packet is dropped. Sharing is by airtime:
each station's guaranteed share is its rate over the number of stations (equal airtime), and what borrowing
adds is bounded by the budget, the fastest station's rate.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from nac_onboard.radio.air_link import AirRadio

DEFAULT_CLASS, BUDGET_CLASS = 0x1, 0x2
PAIR_BASE, PROBE_BASE = 0x100, 0x800
UNSHAPED = "10gbit"
OUT_OF_RANGE_BPS = 1e6  # an out-of-range pair's class rate, when the channel names no minimum: see air_state
QUANTUM_BYTES = 6000


@dataclass(frozen=True)
class AirState:
    """Every ordered pair at one instant; rates in bits per simulated second (0 = out of range)."""

    distance_m: np.ndarray  # (N, N)
    rate_bps: np.ndarray  # (N, N)
    loss: np.ndarray  # (N, N), 0..1
    budget_bps: float | None  # the access point's airtime budget (shared medium only)
    floor_bps: float = OUT_OF_RANGE_BPS  # the lowest rate a class is given (out of range: loss does the work)
    snr_db: np.ndarray | None = None  # (N, N)
    mcs: np.ndarray | None = None  # (N, N), -1 with the Shannon rate model
    frames: dict | None = None  # what a frame-level medium needs: phy_bps, per, fallback_bps, fallback_per (N, N)

    def class_bps(self, i: int, j: int) -> float:
        return max(float(self.rate_bps[i, j]), self.floor_bps)


def air_state(radio: AirRadio, t_s: float, ecef_m: np.ndarray, ap: int | None, sharing: bool,
              heights_m: np.ndarray | None = None) -> AirState:
    """Step the radio to t_s with the vehicles' positions and say what every pair gets."""
    distance, sample = radio.step(t_s, ecef_m, heights_m)
    n = radio.n
    rate = radio.matrix(sample.goodput_bps)
    loss = radio.matrix(sample.loss)
    # Out of range, every packet is dropped; the class keeps the channel's minimum rate, because HTB charges a
    # class for what it sends at its rate: at a few kbit/s one queued packet costs seconds of debt, and the link
    # would stay silent that long after coming back into range.
    floor = radio.radio.model.min_rate_bps or OUT_OF_RANGE_BPS
    if ap is not None and n > 2:
        rate, loss = through_the_ap(rate, loss, ap)
    budget = None
    if sharing and ap is not None and n > 1:
        budget = float(max(np.delete(rate[ap], ap).max(), floor))
    frames = {"phy_bps": radio.matrix(np.where(sample.in_range, sample.phy_bps, 0.0)),
              "per": radio.matrix(sample.per, 1.0), "fallback_bps": radio.matrix(sample.fallback_bps),
              "fallback_per": radio.matrix(sample.fallback_per, 1.0)}
    if ap is not None and n > 2:  # the frame-level medium sends a worker pair's frames once, at its two hops' rate
        frames["phy_bps"], frames["per"] = through_the_ap(frames["phy_bps"], frames["per"], ap)
        frames["fallback_bps"], frames["fallback_per"] = through_the_ap(frames["fallback_bps"],
                                                                        frames["fallback_per"], ap)
    return AirState(radio.matrix(distance), rate, loss, budget, floor, radio.matrix(sample.snr_db),
                    radio.matrix(sample.mcs, -1), frames)


def through_the_ap(rate_bps: np.ndarray, loss: np.ndarray, ap: int) -> tuple[np.ndarray, np.ndarray]:
    """Two stations' pair in an infrastructure network: station-to-station frames go up to the access point and
    down from it (IEEE 802.11's infrastructure BSS), so the pair gets the two hops' air time in series, 1 / (1/up +
    1/down), loses what either hop loses, and is out of range only if a hop is. Their own distance does not matter:
    two workers on either side of the master talk through it, as the MPI job's start-up needs every pair to."""
    up, down = rate_bps[:, ap], rate_bps[ap, :]
    both = (up[:, None] > 0) & (down[None, :] > 0)
    up_s_per_bit, down_s_per_bit = 1.0 / np.where(up > 0, up, np.inf), 1.0 / np.where(down > 0, down, np.inf)
    relayed = np.where(both, 1.0 / (up_s_per_bit[:, None] + down_s_per_bit[None, :] + 1e-300), 0.0)
    relayed_loss = np.where(both, 1.0 - (1.0 - loss[:, ap][:, None]) * (1.0 - loss[ap, :][None, :]), 1.0)
    stations = np.ones(len(up), dtype=bool)
    stations[ap] = False
    pairs = stations[:, None] & stations[None, :] & ~np.eye(len(up), dtype=bool)
    return np.where(pairs, relayed, rate_bps), np.where(pairs, relayed_loss, loss)


def with_replay(state: AirState, ids: list[str], rate_of, t_s: float) -> AirState:
    """The state with each recorded pair's rate replaced by rate_of(a, b, t_s) (None: not recorded, the model's
    stays); a recorded rate below the floor is a link with nothing through it."""
    rate, loss = state.rate_bps.copy(), state.loss.copy()
    n = len(ids)
    for i in range(n):
        for j in range(i + 1, n):
            recorded = rate_of(ids[i], ids[j], t_s)
            if recorded is None:
                continue
            through = recorded >= state.floor_bps
            rate[i, j] = rate[j, i] = recorded if through else 0.0
            loss[i, j] = loss[j, i] = 0.0 if through else 1.0
    budget = state.budget_bps
    if budget is not None:
        budget = float(max(rate.max(), state.floor_bps))
    return dataclasses.replace(state, rate_bps=rate, loss=loss, budget_bps=budget)


MAX_WIRE_BPS = 40e9  # beyond what a veth carries here: unshaped in effect (paper-sim's ~100 Gbit/s)


def _bits(rate_bps: float, speedup: float) -> str:
    return f"{min(rate_bps * speedup, MAX_WIRE_BPS):.0f}bit"


@dataclass(frozen=True)
class Layout:
    """Names and addresses of one kernel network, and which station is the access point."""

    addresses: tuple[str, ...]  # station i's address on the air
    ports: tuple[str, ...]  # station i's port (interface name) in the air namespace
    probe_ports: tuple[int | None, ...]  # station i's throughput server port, if it has one
    ap: int | None
    sharing: bool

    @property
    def n(self) -> int:
        return len(self.addresses)

    def shared(self) -> bool:
        return self.sharing and self.ap is not None

    def _probed(self, j: int) -> bool:
        return self.ap is not None and j != self.ap and self.probe_ports[j] is not None

    # ---- the air namespace: one HTB per bridge port ------------------------------------------------------
    def air_setup(self) -> list[str]:
        lines = []
        for j, port in enumerate(self.ports):
            lines += [f"qdisc add dev {port} root handle 1: htb default {DEFAULT_CLASS:x}",
                      f"class add dev {port} parent 1: classid 1:{DEFAULT_CLASS:x} htb rate {UNSHAPED} "
                      f"quantum {QUANTUM_BYTES}"]
            if self.shared() and j == self.ap:
                lines.append(f"class add dev {port} parent 1: classid 1:{BUDGET_CLASS:x} htb rate {UNSHAPED} "
                             f"quantum {QUANTUM_BYTES}")
            for i in range(self.n):
                if i == j:
                    continue
                lines.append(f"class add dev {port} parent {self._pair_parent(j)} classid 1:{PAIR_BASE + i:x} "
                             f"htb rate {UNSHAPED} quantum {QUANTUM_BYTES}")
                lines.append(f"filter add dev {port} parent 1: protocol ip prio 2 u32 match ip src "
                             f"{self.addresses[i]}/32 flowid 1:{PAIR_BASE + i:x}")
            for i, match in self._probe_flows(j):
                lines.append(f"class add dev {port} parent 1: classid 1:{PROBE_BASE + i:x} htb rate {UNSHAPED} "
                             f"quantum {QUANTUM_BYTES}")
                lines.append(f"filter add dev {port} parent 1: protocol ip prio 1 u32 {match} "
                             f"flowid 1:{PROBE_BASE + i:x}")
        return lines

    def _probe_flows(self, j: int) -> list[tuple[int, str]]:
        """(source, u32 match) of the probe traffic leaving through port j: the access point's probes to j, or
        at the access point's port every station's answers to them (no flow queueing in these kernels, so the
        acknowledgements would otherwise wait behind the MPI job's transfers in the pair's queue)."""
        if self.ap is None:
            return []
        if j != self.ap:
            return [(self.ap, f"match ip src {self.addresses[self.ap]}/32 match ip dport {self.probe_ports[j]} "
                              "0xffff")] if self._probed(j) else []
        return [(i, f"match ip src {self.addresses[i]}/32 match ip sport {self.probe_ports[i]} 0xffff")
                for i in range(self.n) if self._probed(i)]

    def _pair_parent(self, j: int) -> str:
        return f"1:{BUDGET_CLASS:x}" if self.shared() and j == self.ap else "1:"

    def air_update(self, state: AirState, speedup: float) -> list[str]:
        lines = []
        for j, port in enumerate(self.ports):
            if self.shared() and j == self.ap:
                lines.append(self._change(port, "1:", BUDGET_CLASS, state.budget_bps, state.budget_bps, speedup))
            for i in range(self.n):
                if i == j:
                    continue
                rate = ceil = state.class_bps(i, j)
                if self.shared() and j == self.ap:
                    rate = ceil / (self.n - 1)  # an equal share of airtime guaranteed
                lines.append(self._change(port, self._pair_parent(j), PAIR_BASE + i, rate, ceil, speedup))
            for i, _ in self._probe_flows(j):
                pair = state.class_bps(i, j)
                lines.append(self._change(port, "1:", PROBE_BASE + i, pair, pair, speedup))
        return lines

    # ---- the access point's own interface: what it sends shares the budget too ----------------------------
    def ap_setup(self, device: str = "air0") -> list[str]:
        if not self.shared():
            return []
        lines = [f"qdisc add dev {device} root handle 1: htb default {DEFAULT_CLASS:x}",
                 f"class add dev {device} parent 1: classid 1:{DEFAULT_CLASS:x} htb rate {UNSHAPED} "
                 f"quantum {QUANTUM_BYTES}",
                 f"class add dev {device} parent 1: classid 1:{BUDGET_CLASS:x} htb rate {UNSHAPED} "
                 f"quantum {QUANTUM_BYTES}"]
        for j in range(self.n):
            if j == self.ap:
                continue
            if self._probed(j):  # probes pass unshaped here: their own class at j's port holds the pair's rate
                lines.append(f"filter add dev {device} parent 1: protocol ip prio 1 u32 match ip dst "
                             f"{self.addresses[j]}/32 match ip dport {self.probe_ports[j]} 0xffff "
                             f"flowid 1:{DEFAULT_CLASS:x}")
            lines.append(f"class add dev {device} parent 1:{BUDGET_CLASS:x} classid 1:{PAIR_BASE + j:x} htb "
                         f"rate {UNSHAPED} quantum {QUANTUM_BYTES}")
            lines.append(f"filter add dev {device} parent 1: protocol ip prio 2 u32 match ip dst "
                         f"{self.addresses[j]}/32 flowid 1:{PAIR_BASE + j:x}")
        return lines

    def ap_update(self, state: AirState, speedup: float, device: str = "air0") -> list[str]:
        if not self.shared():
            return []
        lines = [self._change(device, "1:", BUDGET_CLASS, state.budget_bps, state.budget_bps, speedup)]
        for j in range(self.n):
            if j != self.ap:
                ceil = state.class_bps(self.ap, j)
                rate = ceil / (self.n - 1)
                lines.append(self._change(device, f"1:{BUDGET_CLASS:x}", PAIR_BASE + j, rate, ceil, speedup))
        return lines

    @staticmethod
    def _change(device: str, parent: str, classid: int, rate_bps: float, ceil_bps: float, speedup: float) -> str:
        return (f"class change dev {device} parent {parent} classid 1:{classid:x} htb rate "
                f"{_bits(rate_bps, speedup)} ceil {_bits(max(ceil_bps, rate_bps), speedup)} quantum {QUANTUM_BYTES}")

    # ---- loss: nftables in the bridge ------------------------------------------------------------------
    @staticmethod
    def nft_setup(table: str) -> str:
        return f"table bridge {table} {{ chain loss {{ type filter hook forward priority 0; policy accept; }}; }}\n"

    def nft_update(self, table: str, state: AirState) -> str:
        """One line, one transaction: the chain emptied and refilled with a rule per lossy pair."""
        commands = [f"flush chain bridge {table} loss"]
        for i in range(self.n):
            for j in range(self.n):
                loss = float(state.loss[i, j])
                if i == j or loss <= 0:
                    continue
                match = f"ip saddr {self.addresses[i]} ip daddr {self.addresses[j]}"
                if loss >= 1:
                    commands.append(f"add rule bridge {table} loss {match} drop")
                else:
                    commands.append(f"add rule bridge {table} loss {match} numgen random mod 10000 < "
                                    f"{round(loss * 10000)} drop")
        return "; ".join(commands) + "\n"
