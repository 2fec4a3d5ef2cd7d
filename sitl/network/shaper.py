"""The link shaper: every `period_s` of simulated time it reads the vehicles' true positions, asks the channel
model for each pair's rate and loss (sitl.network.shaping) and applies them to the kernel network, changing HTB
classes in place (their queues are kept) and refilling the nftables loss chain. Each update is a record in
network.jsonl (simulated and wall time, per pair: distance, rate in bits per simulated second, loss), which the
analysis compares with what the probes measured. A shaper that falls behind says so and keeps the last rates.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from nac_onboard.flight_log import JsonlLog
from nac_onboard.radio.air_link import AirRadio
from nac_onboard.radio.channel import ChannelModel
from nac_onboard.records import kinds
from sitl.network.air import AirNetwork
from sitl.network.netns import NetworkError
from sitl.network.shaping import AirState, air_state, with_replay

log = logging.getLogger(__name__)
LATE_LOG_EVERY_S = 5.0  # wall seconds between "falling behind" records


class Shaper:
    def __init__(self, air: AirNetwork, positions: Callable[[], tuple], channel: ChannelModel,
                 speedup: float | Callable[[], float], period_s: float, out: JsonlLog, replay=None):
        """positions: () -> (simulated time, earth-centred positions (N, 3)[, heights above ground (N,)]).
        replay: a nac_onboard.radio.replay.ReplayLinks whose recorded pairs override the model's rates.
        speedup: the simulator's pace, or what measures it (nac_onboard.clock.Pace.value): rates on the
        wire are the model's times the pace at each update."""
        self.air, self.positions, self.channel = air, positions, channel
        self.radio = AirRadio(channel, len(air.stations))
        self.replay = replay
        self.ids = [s.vehicle_id for s in air.stations]
        self.pace = speedup if callable(speedup) else (lambda: speedup)
        self.period_s, self.out = period_s, out
        self.updates = self.late = 0
        self.apply_s: list[float] = []  # wall seconds from reading positions to the last line written
        self.last: AirState | None = None
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="link-shaper", daemon=True)
        self._last_late_log = -1e9

    def start(self) -> Shaper:
        self.update()  # the first rates are in place before anything is sent
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)

    def _run(self) -> None:
        next_at = time.monotonic() + self.period_s / self.pace()
        while not self._stop.wait(max(next_at - time.monotonic(), 0.0)):
            try:
                self.update()
            except NetworkError as err:  # tc or nft died: the links keep their last rates
                self.error = str(err)
                self.out.write(kinds.SHAPER_FAILED, error=str(err))
                log.error("link shaper stopped: %s", err)
                return
            next_at += self.period_s / self.pace()
            behind_s = time.monotonic() - next_at
            if behind_s > 0:
                self.late += 1
                if time.monotonic() - self._last_late_log >= LATE_LOG_EVERY_S:
                    self._last_late_log = time.monotonic()
                    self.out.write(kinds.SHAPER_LATE, behind_s=round(behind_s, 4), late_updates=self.late,
                                   note="rates are updated less often than every period; the last ones hold")
                next_at = time.monotonic()  # skip the missed ticks rather than burst through them

    def update(self) -> AirState:
        t0 = time.monotonic()
        t_sim_s, ecef, *heights = self.positions()
        layout = self.air.layout
        state = air_state(self.radio, t_sim_s, ecef, layout.ap, layout.sharing, heights[0] if heights else None)
        if self.replay is not None:
            state = with_replay(state, self.ids, self.replay.rate_bps, t_sim_s)
        pace = self.pace()
        self.air.apply(state, pace)
        self.apply_s.append(time.monotonic() - t0)
        self.updates += 1
        self.last = state
        self._record(t_sim_s, state, pace)
        return state

    def _record(self, t_sim_s: float, state: AirState, pace: float) -> None:
        ids = self.ids
        n = len(ids)
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
        self.out.write(kinds.LINK_RATES, t_sim_s=round(t_sim_s, 3), speedup=round(pace, 4),
                       a=[ids[i] for i, _ in pairs], b=[ids[j] for _, j in pairs],
                       distance_m=[round(float(state.distance_m[i, j]), 3) for i, j in pairs],
                       rate_bps=[round(float(state.rate_bps[i, j])) for i, j in pairs],
                       loss=[round(float(state.loss[i, j]), 6) for i, j in pairs],
                       snr_db=[round(float(state.snr_db[i, j]), 2) for i, j in pairs],
                       mcs=[int(state.mcs[i, j]) for i, j in pairs],
                       budget_bps=None if state.budget_bps is None else round(state.budget_bps),
                       source=f"replay:{self.replay.source}" if self.replay else self.channel.name)
