"""The figures of a run: one drawing function per figure, each on a given matplotlib Axes, so a report draws
one run per figure and a comparison draws two runs side by side with the same code."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display on a companion computer or in CI
import matplotlib.pyplot as plt  # noqa: E402

from ground.logs.analysis import RunTables  # noqa: E402


def _empty(ax, what: str) -> None:
    ax.text(0.5, 0.5, f"no {what} in this run", ha="center", va="center", transform=ax.transAxes)


def trajectories(ax, t: RunTables) -> None:
    ax.set(title="Trajectories (from above)", xlabel="east (m)", ylabel="north (m)")
    if t.trajectories.empty:
        return _empty(ax, "positions")
    for vehicle, track in t.trajectories.groupby("vehicle"):
        label = f"{vehicle} (master)" if vehicle == t.master else vehicle
        line, = ax.plot(track["east_m"], track["north_m"], label=label)
        ax.plot(track["east_m"].iloc[0], track["north_m"].iloc[0], "o", color=line.get_color())
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize="small")


def time_label(t: RunTables) -> str:
    """A SITL run's axis is its simulated time at any speed-up; a flight's, its own."""
    return "simulated time (s)" if t.clock.simulated else "time (s)"


def distances(ax, t: RunTables) -> None:
    ax.set(title="Master-worker distance", xlabel=time_label(t), ylabel="distance (m)")
    if t.distances.empty:
        return _empty(ax, "distances")
    for worker, rows in t.distances.groupby("worker"):
        ax.plot(rows["t_rel_s"], rows["distance_m"], label=f"{t.master} - {worker}")
    ax.legend(fontsize="small")


def throughput_over_time(ax, t: RunTables) -> None:
    ax.set(title="Throughput over time", xlabel=time_label(t), ylabel="throughput (Mbit/s)")
    if t.throughput.empty:
        return _empty(ax, "throughput probes")
    for (client, server), rows in t.throughput.groupby(["client", "server"]):
        ax.plot(rows["t_rel_s"], rows["throughput_mbps"], ".-", label=f"{client} -> {server}")
    ax.legend(fontsize="small")


def throughput_vs_distance(ax, t: RunTables) -> None:
    ax.set(title="Throughput vs distance", xlabel="distance (m)",
           ylabel="throughput (Mbit/s)")
    if t.throughput_by_distance.empty:
        return _empty(ax, "throughput probes with distances")
    b = t.throughput_by_distance
    middle = (b["distance_from_m"] + b["distance_to_m"]) / 2
    ax.fill_between(middle, b["p2_5_mbps"], b["p97_5_mbps"], alpha=0.2, label="95 % of probes")
    ax.errorbar(middle, b["mean_mbps"], yerr=b["std_mbps"], fmt="o-", capsize=3, label="mean ± std")
    ax.legend(loc="upper right")
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)


def iteration_time(ax, t: RunTables) -> None:
    ax.set(title="Iteration time", xlabel=time_label(t), ylabel="iteration duration (s)")
    if t.iterations.empty:
        return _empty(ax, "compute iterations")
    its = t.iterations
    ax.plot(its["t_rel_s"], its["duration_s"], ".", markersize=3, label="all workers present")
    partial = its[its["absent"] != ""]
    if not partial.empty:
        ax.plot(partial["t_rel_s"], partial["duration_s"], "x", color="tab:red", label="a worker absent")
    _mark_events(ax, t.events, "t_rel_s")
    ax.legend(fontsize="small")


def _mark_events(ax, events, column: str) -> None:
    """A faint vertical line and its words at each fault and MPI job restart (column: the axis's quantity)."""
    for _, e in events.dropna(subset=[column]).iterrows():
        ax.axvline(e[column], color="tab:gray", linestyle=":", linewidth=1)
        ax.annotate(e["what"], (e[column], 1.0), xycoords=("data", "axes fraction"), rotation=90, fontsize="x-small",
                    va="top", ha="right", color="tab:gray")


def time_per_10_vs_distance(ax, t: RunTables) -> None:
    ax.set(title="Time per 10 iterations", xlabel="master-worker distance (m)", ylabel="time per 10 iterations (s)")
    if t.time_per_10.empty:
        return _empty(ax, "blocks of 10 iterations with a worker present")
    for worker, blocks in t.time_per_10.groupby("worker"):
        dots = ax.plot(blocks["distance_m"], blocks["time_per_10_s"], ".", markersize=3, alpha=0.5)
        bins = t.time_per_10_by_distance[t.time_per_10_by_distance["worker"] == worker]
        middle = (bins["distance_from_m"] + bins["distance_to_m"]) / 2
        ax.plot(middle, bins["median_s"], "-o", color=dots[0].get_color(), markersize=4, label=f"{worker}: median")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize="small")


def training_cost(ax, t: RunTables) -> None:
    ax.set(title="Training cost", xlabel="iteration", ylabel="cost (mean squared error / 2)")
    if t.training_cost.empty:
        return _empty(ax, "training cost (linear regression)")
    ax.plot(t.training_cost["iteration"], t.training_cost["cost"])
    # a fault before the job's first iteration (a slow MPI start) ran during no iteration: its mark goes at the
    # first one, the first the fault could have slowed, so that the figure still shows it
    _mark_events(ax, t.events.fillna({"iteration": t.training_cost["iteration"].iloc[0]}), "iteration")


def power(ax, t: RunTables) -> None:
    """Each vehicle's flight power (solid) and companion pack's output (dashed), once a simulated second."""
    ax.set(title="Power", xlabel="simulated time (s)", ylabel="power (W)")
    if t.energy.empty:
        return _empty(ax, "energy records")
    for vehicle, rows in t.energy.groupby("vehicle", sort=False):
        line, = ax.plot(rows["t_sim_s"], rows["flight_w"], label=f"{vehicle}: flight")
        ax.plot(rows["t_sim_s"], rows["companion_w"], "--", color=line.get_color(), label=f"{vehicle}: companion")
    ax.set_yscale("symlog", linthresh=10.0)
    ax.legend(fontsize="x-small", ncol=2)


FIGURES = {"trajectories": trajectories, "distances": distances, "throughput_over_time": throughput_over_time,
           "throughput_vs_distance": throughput_vs_distance, "iteration_time": iteration_time,
           "time_per_10_vs_distance": time_per_10_vs_distance, "training_cost": training_cost, "power": power}
ONLY_WITH_DATA = {"power": lambda t: not t.energy.empty}  # drawn only when the run has what they show


def draw(name: str, runs: list[RunTables], path: Path) -> Path:
    """One figure file: the named plot for each run, side by side with shared axes when there are several."""
    fig, axes = plt.subplots(1, len(runs), figsize=(6.4 * len(runs), 4.8), squeeze=False,
                             sharex=len(runs) > 1 and name != "trajectories", sharey=len(runs) > 1)
    for ax, run in zip(axes[0], runs, strict=True):
        FIGURES[name](ax, run)
        ax.grid(alpha=0.3)
        if len(runs) > 1:
            ax.set_title(f"{run.name}: {ax.get_title()}")
    _margins(fig)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _margins(fig) -> None:
    """Fixed margins that hold the titles, tick labels and axis labels these figures draw: tight_layout measured
    every text first and cost a third of each report's time (0.13 of 0.35 s a figure)."""
    fig.subplots_adjust(left=0.1 if len(fig.axes) == 1 else 0.06, right=0.97, bottom=0.11, top=0.92, wspace=0.18)


def draw_iteration_time_distribution(runs: list[RunTables], path: Path) -> Path:
    """The runs' iteration times as distributions on one axes (the share of iterations done within each time), so
    a comparison shows the whole spread, tail included, not only a median: a straggler shows as the tail."""
    import numpy as np

    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    ax.set(title="Iteration time distribution", xlabel="iteration duration (s, simulated)",
           ylabel="share of iterations done within")
    drawn = False
    for run in runs:
        durations = np.empty(0) if run.iterations.empty else run.iterations["duration_s"].dropna().to_numpy(float)
        durations = np.sort(durations[durations > 0])  # a log axis
        if len(durations):
            share = np.arange(1, len(durations) + 1) / len(durations)
            ax.step(durations, share, where="post", label=f"{run.name}: {len(durations)} timed iterations")
            drawn = True
    if drawn:
        ax.set_xscale("log")
        ax.legend(fontsize="small")
    else:
        _empty(ax, "compute iterations")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3, which="both")
    _margins(fig)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def draw_calibration(probes, model, path: Path) -> Path:
    """Measured probes against the fitted radio's median and 95 % band by distance."""
    import numpy as np

    from nac_onboard.radio.air_link import rate_band

    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    d = probes["distance_m"].astype(float)
    ax.scatter(d, probes["throughput_mbps"], s=10, alpha=0.5, label="measured probes")
    grid = np.linspace(max(float(d.min()) * 0.8, 0.5), float(d.max()) * 1.1, 80)
    band = rate_band(model, grid, draws=500)
    ax.fill_between(grid, band["low_bps"] / 1e6, band["high_bps"] / 1e6, alpha=0.2, label="fitted: 95 % band")
    ax.plot(grid, band["median_bps"] / 1e6, label="fitted: median")
    ax.set(title=f"Calibration: {model.name}", xlabel="distance (m)", ylabel="throughput (Mbit/s)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend()
    _margins(fig)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
