"""Fault injection in an experiment: what each scenario fault kind does, and when it is undone.

Link, GPS, battery and loss faults go through the simulator's fault API (sitl/server.py), which sets the
vehicle's SIM_* parameters (sitl/vehicle/params.py); the vehicle's flight logic reacts as an autopilot would
(sitl/vehicle/guards.py: GPS lost -> land, low battery -> BATT_FS_LOW_ACT). Process faults kill the vehicle's
agent or its MPI rank, as a crash on the companion computer would; companion faults take the whole companion
computer away (and back), which the experiment runner does (it owns the processes and the network).
"""

from __future__ import annotations

import logging
import os
import signal
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from nac_onboard.flight_log import read_jsonl
from nac_onboard.records import kinds
from sitl.server import Sitl
from sitl.vehicle.world import COMPANION

log = logging.getLogger(__name__)


class FaultKind(Enum):
    LINK_DOWN = "link_down"  # the companion MAVLink link stops both ways; value unused
    GPS_LOST = "gps_lost"  # no fix: position frozen, the vehicle lands (EKF failsafe)
    BATTERY_PCT = "battery_pct"  # the battery at `value` %: below BATT_LOW_PCT the failsafe acts
    PACKET_LOSS_PCT = "packet_loss_pct"  # `value` % of the companion link's packets lost both ways
    KILL_AGENT = "kill_agent"  # the onboard agent is SIGKILLed (not restarted)
    KILL_WORKER = "kill_worker"  # the vehicle's MPI rank is SIGKILLed
    # the companion computer gone (brown-out, reset, router dead): every process on it killed, its Wi-Fi down
    LOSE_COMPANION = "lose_companion"
    # the same, then back after duration_s: Wi-Fi up, its agent started again as systemd would, and its rank
    # back in the MPI job (which the experiment restarts from its checkpoint with the workers present)
    REBOOT_COMPANION = "reboot_companion"


@dataclass(frozen=True)
class Fault:
    at_s: float  # simulated seconds after the missions start
    vehicle: str
    kind: FaultKind
    duration_s: float = 0.0  # 0: until the end
    value: float = 0.0


class FaultInjector:
    """Applies scenario faults to vehicle `index` of the running simulator and processes."""

    def __init__(self, sim: Sitl, kill_agent: Callable[[int], None], rank_log: Callable[[str], Path],
                 companion: Callable[[int, bool], None]):
        self.sim = sim
        self.kill_agent = kill_agent  # index -> None
        self.rank_log = rank_log  # vehicle id -> its MPI rank's log (which names the rank's pid)
        self.companion = companion  # (index, up): the companion computer lost (False) or back (True)

    def apply(self, fault: Fault, index: int, on: bool) -> None:
        kind = fault.kind
        if kind is FaultKind.LINK_DOWN:
            self.sim.set_link_down(index, COMPANION, on)
        elif kind is FaultKind.GPS_LOST:
            self.sim.set_gps_lost(index, on)
        elif kind is FaultKind.PACKET_LOSS_PCT:
            self.sim.set_loss(index, COMPANION, fault.value if on else 0.0)
        elif kind is FaultKind.BATTERY_PCT and on:
            self.sim.set_battery_pct(index, fault.value)
        elif kind is FaultKind.KILL_AGENT and on:
            self.kill_agent(index)
        elif kind is FaultKind.KILL_WORKER and on:
            self._kill_rank(fault.vehicle)
        elif kind is FaultKind.LOSE_COMPANION and on:
            self.companion(index, False)
        elif kind is FaultKind.REBOOT_COMPANION:
            self.companion(index, not on)

    def _kill_rank(self, vehicle_id: str) -> None:
        path = self.rank_log(vehicle_id)
        try:
            started = read_jsonl(path).of_kind(kinds.WORKER_STARTED)
            if not started:
                raise OSError(f"{path} has no {kinds.WORKER_STARTED} record yet")
            os.kill(int(started[-1]["pid"]), signal.SIGKILL)
        except (OSError, KeyError, ValueError) as err:
            log.warning("kill_worker %s: %s", vehicle_id, err)
