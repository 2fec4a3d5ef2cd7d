"""Where the workers are relative to the master, for link emulation: the agent's live feed, or a script.

A source answers distances_m(iteration, elapsed_s) -> {worker rank: metres or None (unknown)}.
  FixedDistances    one distance per worker (static scenarios, tests)
  ScriptedDistances piecewise-constant distances by iteration or by time, from a JSON file:
                    {"by": "iteration", "distances_m": {"1": [[0, 10.0]], "2": [[0, 10.0], [50, 40.0], [80, 10.0]]}}
                    (worker 2 is 10 m away until iteration 50, 40 m until 80, then 10 m again)
  FeedDistances     the local agent's state feed: rank r is vehicle ids[r]; the master is rank 0
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from nac_onboard.agent.state_feed import StateFeedError, distance_between, fetch_state
from nac_onboard.errors import BadInput
from nac_onboard.inputs import MAX_CONFIG_BYTES, read_bounded_text


class PositionsError(BadInput):
    pass


class FixedDistances:
    def __init__(self, distances_m: list[float]):
        self.distances = {rank: d for rank, d in enumerate(distances_m, start=1)}

    def distances_m(self, iteration: int, elapsed_s: float) -> dict[int, float | None]:
        return dict(self.distances)

    restarted: frozenset = frozenset()  # no agents to restart

    def lost_ranks(self) -> set[int]:
        return set()  # no agents to lose


class ScriptedDistances:
    def __init__(self, by: str, schedule: dict[int, list[tuple[float, float]]]):
        if by not in ("iteration", "time_s"):
            raise PositionsError(f"positions script: 'by' must be 'iteration' or 'time_s', got {by!r}")
        for rank, points in schedule.items():
            for at, d in points:  # NaN or infinity would become a NaN link time, or an endless sleep
                if not (math.isfinite(at) and at >= 0 and math.isfinite(d) and 0 <= d <= 1e6):
                    raise PositionsError(f"positions script: rank {rank}: [{at!r}, {d!r}]: expected a finite time "
                                         ">= 0 and a distance within [0, 1000000] m")
        self.by, self.schedule = by, {rank: sorted(points) for rank, points in schedule.items()}

    @classmethod
    def load(cls, path: str | Path) -> ScriptedDistances:
        try:
            data = json.loads(read_bounded_text(path, "positions script", MAX_CONFIG_BYTES, PositionsError))
            schedule = {int(rank): [(float(at), float(d)) for at, d in points]
                        for rank, points in data["distances_m"].items()}
            return cls(data.get("by", "iteration"), schedule)
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise PositionsError(f"{path}: expected {{\"by\": \"iteration\", \"distances_m\": {{\"1\": [[0, 10.0]], "
                                 f"...}}}}: {err}") from None

    def distances_m(self, iteration: int, elapsed_s: float) -> dict[int, float | None]:
        at = iteration if self.by == "iteration" else elapsed_s
        out = {}
        for rank, points in self.schedule.items():
            current = None
            for start, distance in points:
                if start <= at:
                    current = distance
            out[rank] = current
        return out

    restarted: frozenset = frozenset()  # no agents to restart

    def lost_ranks(self) -> set[int]:
        return set()  # no agents to lose


class FeedDistances:
    def __init__(self, address: str, vehicle_ids: list[str], timeout_s: float = 0.3):
        if len(vehicle_ids) < 2:
            raise PositionsError("--vehicles needs the master's id then one id per worker, in rank order")
        self.address, self.ids, self.timeout_s = address, vehicle_ids, timeout_s
        self.failures = 0
        self.state: dict = {}  # the last answer
        self.boots: dict[int, str] = {}  # each worker's agent boot as this job first heard it
        self.restarted: set[int] = set()  # workers heard with another boot since: their ranks are gone

    def distances_m(self, iteration: int, elapsed_s: float) -> dict[int, float | None]:
        try:
            self.state = fetch_state(self.address, self.timeout_s)
        except StateFeedError:
            self.failures += 1
            self.state = {}
            return {rank: None for rank in range(1, len(self.ids))}
        lost = self.lost_ranks()  # a lost peer's last position is not where it is
        return {rank: None if rank in lost else distance_between(self.state, self.ids[0], vehicle)
                for rank, vehicle in enumerate(self.ids[1:], start=1)}

    def lost_ranks(self) -> set[int]:
        """The workers whose agents the master's agent has lost (silent for its peers.timeout_s, or forgotten
        since) in the last answer, or hears with another boot than this job first heard (the companion restarted:
        its rank is gone, and a send to the old connection is answered by a reset, which crashes UCX's TCP
        transport): not sent work, sooner than the job's own deadlines would find them gone; the lost ones until
        heard again, the restarted ones for good (the job's supervisor starts the job again with them)."""
        peers = self.state.get("peers") or {}
        out = set()
        for rank, vehicle in enumerate(self.ids[1:], start=1):
            peer = peers.get(vehicle)
            if not isinstance(peer, dict):
                if rank in self.boots and self.state:  # heard by this job, then forgotten by the agent (forget_s)
                    out.add(rank)
                continue
            boot = peer.get("boot")
            first = self.boots.setdefault(rank, boot) if isinstance(boot, str) and boot else self.boots.get(rank)
            if isinstance(boot, str) and boot and boot != first:
                self.restarted.add(rank)
            if peer.get("lost") is True or rank in self.restarted:
                out.add(rank)
        return out

    def measured_rates_bps(self, max_age_s: float) -> dict[int, float | None]:
        """Each worker's rate as the master's agent last measured it (its probes in the last answer), if no older
        than max_age_s wall seconds; None where there is none. A value that is not a finite rate is none."""
        probes = self.state.get("probes") if isinstance(self.state, dict) else None
        out: dict[int, float | None] = {}
        for rank, vehicle in enumerate(self.ids[1:], start=1):
            probe = probes.get(vehicle) if isinstance(probes, dict) else None
            bps, age = (probe.get("bits_per_second"), probe.get("age_s")) if isinstance(probe, dict) else (None, None)
            fresh = all(isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) and x >= 0
                        for x in (bps, age)) and age <= max_age_s
            out[rank] = float(bps) if fresh else None
        return out


def wait_for_feed(source: FeedDistances, timeout_s: float) -> None:
    """Block until the feed knows every vehicle's position (an experiment starts before GPS is everywhere)."""
    deadline = time.monotonic() + timeout_s
    while True:
        if all(d is not None for d in source.distances_m(0, 0.0).values()):
            return
        if time.monotonic() > deadline:
            raise PositionsError(f"the state feed at {source.address} did not know all of {', '.join(source.ids)} "
                                 f"within {timeout_s:g} s")
        time.sleep(0.2)
