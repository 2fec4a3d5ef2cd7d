"""The experiment's energy meter: once a simulated second, each vehicle's flight power (the simulator's flight pack,
sitl/vehicle/energy.py), its companion's compute power (its MPI rank's CPU time, read from /proc) and radio power
(its station's bytes, read from the kernel's counters in its namespace), and the companion pack the two drain.

A rank's host CPU seconds become the companion's busy seconds on the run's clock: at a speed-up the host's second
is `speedup` simulated seconds, and with a device profile the job holds each result until the device's time has
passed (nac_onboard/compute/device.py), so busy = CPU x max(slowdown, speedup). The meter only measures and
decides; the runner acts on a pack that empties (its agent, rank and radio stop).
"""

from __future__ import annotations

import os
from dataclasses import asdict

from nac_onboard.flight_log import JsonlLog
from nac_onboard.records import kinds
from sitl.vehicle import energy

TICK_S = 1.0  # simulated seconds between records
_CLOCK_TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def process_cpu_s(pid: int | None) -> float | None:
    """User plus system CPU seconds of a live process (all its threads), or None."""
    if pid is None:
        return None
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / _CLOCK_TICKS_PER_S  # utime, stime: fields 14 and 15
    except (OSError, IndexError, ValueError):
        return None


def namespace_bytes(pid: int | None) -> tuple[int, int] | None:
    """(received, sent) bytes over every interface but loopback in the network namespace of process pid."""
    if pid is None:
        return None
    try:
        with open(f"/proc/{pid}/net/dev") as f:
            lines = f.read().splitlines()[2:]
    except OSError:
        return None
    rx = tx = 0
    for line in lines:
        name, _, counters = line.partition(":")
        values = counters.split()
        if name.strip() != "lo" and len(values) >= 9:
            rx, tx = rx + int(values[0]), tx + int(values[8])
    return rx, tx


class EnergyMeter:
    def __init__(self, vehicle_ids: list[str], plan, companion_mah: list[float], frames: list[str], log: JsonlLog,
                 slowdowns: list[float], radio_counted: bool):
        self.ids, self.log, self.slowdowns = vehicle_ids, log, slowdowns  # each companion's device profile
        self.companion, self.radio = energy.COMPANIONS[plan.companion], energy.RADIOS[plan.radio]
        self.efficiency = plan.dc_dc_efficiency
        self.packs = [energy.Pack(plan.companion_cells, mah) for mah in companion_mah]
        self.radio_counted = radio_counted
        self.empty = [False] * len(vehicle_ids)
        self._t_s: float | None = None
        self._flight_wh: list[float] = []
        self._cpu_s: list[float | None] = [None] * len(vehicle_ids)
        self._bytes: list[tuple[int, int] | None] = [None] * len(vehicle_ids)
        log.write(kinds.ENERGY_PLAN, frames=dict(zip(vehicle_ids, frames, strict=True)),
                  companion=asdict(self.companion), radio=asdict(self.radio),
                  companion_packs={v: [p.cells, p.capacity_mah] for v, p in zip(vehicle_ids, self.packs, strict=True)},
                  dc_dc_efficiency=self.efficiency, radio_counted=radio_counted)

    def due(self, t_sim_s: float) -> bool:
        """Whether tick would record: the first call, or TICK_S after the last record."""
        return self._t_s is None or t_sim_s - self._t_s >= TICK_S

    def tick(self, t_sim_s: float, flight: list[dict], cpu_s: list[float | None],
             net_bytes: list[tuple[int, int] | None], speedup: float,
             rates_bps: list[float | None] | None = None) -> list[int]:
        """Records for the interval since the last tick, once TICK_S has passed; the vehicles whose companion pack
        emptied in it. flight: each vehicle's flight pack (consumed_wh, soc, voltage_v); cpu_s: its rank's CPU seconds
        (None: no rank or not known yet); net_bytes: its namespace's (rx, tx) bytes (None: not counted); rates_bps:
        the rate of each station's link now, in bits per simulated second (None: the radio's PHY rate), so a slow
        link at distance keeps the radio on longer for the same bytes."""
        if self._t_s is None:
            self._t_s, self._flight_wh = t_sim_s, [f["consumed_wh"] for f in flight]
            self._cpu_s, self._bytes = list(cpu_s), list(net_bytes)
            return []
        dt_s = t_sim_s - self._t_s
        if dt_s < TICK_S:
            return []
        emptied = []
        for i, vehicle in enumerate(self.ids):
            busy = self._share(cpu_s[i], self._cpu_s[i], max(self.slowdowns[i], speedup) / dt_s)
            rx_share = tx_share = 0.0
            rate_bps = (rates_bps[i] if rates_bps else None) or self.radio.phy_rate_bps
            if self.radio_counted and net_bytes[i] is not None and self._bytes[i] is not None:
                per_byte = 8.0 / (rate_bps * dt_s)
                rx_share = self._share(net_bytes[i][0], self._bytes[i][0], per_byte)
                tx_share = self._share(net_bytes[i][1], self._bytes[i][1], per_byte)
            on = not self.empty[i]
            compute_w = energy.companion_power_w(self.companion, busy) if on else 0.0
            radio_w = energy.radio_power_w(self.radio, tx_share, rx_share) if on else 0.0
            companion_w = (compute_w + radio_w) / self.efficiency
            pack = self.packs[i]
            _, volts = pack.drain(companion_w, dt_s)
            if on and pack.soc <= 0.0:
                self.empty[i] = True
                emptied.append(i)
            self.log.write(kinds.ENERGY, t_sim_s=round(t_sim_s, 3), dt_s=round(dt_s, 6), vehicle=vehicle,
                           flight_w=round((flight[i]["consumed_wh"] - self._flight_wh[i]) * 3600.0 / dt_s, 4),
                           compute_w=round(compute_w, 4), radio_w=round(radio_w, 4), companion_w=round(companion_w, 4),
                           busy_share=round(busy, 4), tx_share=round(tx_share, 5), rx_share=round(rx_share, 5),
                           air_rate_bps=round(rate_bps),
                           flight_soc=round(flight[i]["soc"], 5), flight_v=round(flight[i]["voltage_v"], 3),
                           companion_soc=round(pack.soc, 5), companion_v=round(volts, 3))
        self._t_s, self._flight_wh = t_sim_s, [f["consumed_wh"] for f in flight]
        self._cpu_s = [c if c is not None else old for c, old in zip(cpu_s, self._cpu_s, strict=True)]
        self._bytes = [b if b is not None else old for b, old in zip(net_bytes, self._bytes, strict=True)]
        return emptied

    @staticmethod
    def _share(now: float | None, before: float | None, scale: float) -> float:
        if now is None or before is None:
            return 0.0
        return min(max((now - before) * scale, 0.0), 1.0)
