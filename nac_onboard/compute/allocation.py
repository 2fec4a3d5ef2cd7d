"""How the master shares the task's rows among the workers (--allocation) and when it plans them again
(--replan-every): shares from the links it expects (the channel model at the positions, or the master's agent's
latest probes in flight) and each worker's device; no MPI here, the runner sends the plan."""

from __future__ import annotations

from nac_onboard.compute import kernels
from nac_onboard.compute.iteration import IterationLinks
from nac_onboard.compute.options import PROBE_MAX_AGE_S, ComputeOptions
from nac_onboard.radio.files import load_replay


class Planner:
    def __init__(self, options: ComputeOptions, workers: list[int], task, source):
        self.options, self.workers, self.task, self.source = options, workers, task, source
        self.replay = load_replay(options.channel.replay_file) if options.channel.replay_file else None
        self.planned_out: frozenset = frozenset()  # the workers the blocks were last planned without
        self.rates_bps: list = []  # what the last plan expected of each link (capacity, speed)
        self._row_cost: tuple[float, float] | None = None  # the task's (CPU s, result bits) per row on this host

    def expected_rates_bps(self, distances: dict) -> list[float | None]:
        """Each worker's link as the allocation expects it: the channel model's capacity at its distance (0 out of
        range; on a kernel network the job does not emulate the links, but the model is the one the air is shaped
        by; see _predicted_bps), or with --link-rates probes its latest probe where one is fresh; None without a
        position."""
        o = self.options
        measured = self.source.measured_rates_bps(o.clock.wall_s(PROBE_MAX_AGE_S)) \
            if o.link_rates == "probes" and self.source is not None else {}
        rates = []
        for rank in self.workers:
            d = distances.get(rank) if distances else None
            predicted = None if d is None else self._predicted_bps(d, (o.vehicle_of(0), o.vehicle_of(rank)))
            rates.append(measured[rank] if measured.get(rank) is not None else predicted)
        return rates

    def _predicted_bps(self, distance_m: float, ids: tuple[str, str]) -> float:
        """A replay table's rate now where it recorded the pair, else the model's median rate at the distance:
        no shadowing or fading draw and the rate adaptation settled, as the plan is for the iterations ahead (a
        stateful look here would lag behind by the time since the last plan, so a plan would depend on when it was
        made); 0 out of range."""
        channel = self.options.channel
        recorded = None if self.replay is None else self.replay.rate_bps(ids[0], ids[1], self.options.clock.now_s())
        rate = channel.capacity_bps(distance_m) if recorded is None else recorded
        return rate if channel.usable(rate) else 0.0

    def shares(self, distances: dict) -> list[float]:
        """Each worker's share of the task's rows by --allocation, at these positions."""
        o = self.options
        if o.allocation == "energy":
            return list(o.energy_wh)
        if o.allocation == "equal":
            return [1.0] * len(self.workers)
        self.rates_bps = rates = self.expected_rates_bps(distances)
        if o.allocation == "capacity":
            return [rate or 0.0 for rate in rates]
        if self._row_cost is None:  # timed once, at the first plan: not again on the master's loop at each re-plan
            self._row_cost = self.task.row_cost()
        cpu_s, bits = self._row_cost  # speed: rows per second, from the device's CPU and the link's time
        return [0.0 if rate == 0.0 else 1.0 / (cpu_s * o.device_for(rank).slowdown + (bits / rate if rate else 0.0)
                                                + 1e-12)
                for rank, rate in zip(self.workers, rates, strict=True)]

    def blocks(self, distances: dict, current: list, planned_out: frozenset = frozenset()) -> tuple[list, list]:
        """(shares, blocks) of the task's rows, those planned out given nothing; if no one is left with a share,
        equal among the rest (and, with no one at all, the `current` blocks)."""
        shares = [0.0 if rank in planned_out else share
                  for rank, share in zip(self.workers, self.shares(distances), strict=True)]
        if sum(shares) <= 0:
            shares = [0.0 if rank in planned_out else 1.0 for rank in self.workers]
        if sum(shares) <= 0:
            return shares, current
        return shares, kernels.split_rows(self.task.rows(), shares)

    def why_now(self, iteration: int, links: IterationLinks) -> str | None:
        """Whether to plan again before this iteration: "absent" (a worker left: absent or unresponsive), "back"
        (one returned), "period" (every --replan-every iterations), or None; remembers who was left out."""
        out = frozenset(r for r in self.workers if not links.present(r))
        why = "absent" if out - self.planned_out else "back" if self.planned_out - out else \
            "period" if iteration and iteration % self.options.replan_every == 0 else None
        if why is not None:
            self.planned_out = out
        return why
