"""A run's energy: the experiment's energy records (sitl/experiment/energy_meter.py, one per vehicle per simulated
second) as tables: the power of each vehicle over time, each vehicle's energy by what used it (flight, compute,
radio) and its packs at the end, and what an iteration and a unit of training progress cost (pure)."""

from __future__ import annotations

import pandas as pd

POWER_COLUMNS = ["t_sim_s", "dt_s", "vehicle", "flight_w", "compute_w", "radio_w", "companion_w", "busy_share",
                 "tx_share", "rx_share", "flight_soc", "flight_v", "companion_soc", "companion_v"]
VEHICLE_COLUMNS = ["vehicle", "flight_wh", "compute_wh", "radio_wh", "companion_wh", "total_wh", "flight_soc_end",
                   "companion_soc_end", "companion_empty_at_s"]
WH_PER_J = 1 / 3600.0


def power(records: list[dict]) -> pd.DataFrame:
    """One row per vehicle and interval."""
    if not records:
        return pd.DataFrame(columns=POWER_COLUMNS)
    return pd.DataFrame.from_records(records)[POWER_COLUMNS]


def by_vehicle(table: pd.DataFrame, emptied: list[dict]) -> pd.DataFrame:
    """Each vehicle's energy (Wh): the integral of its recorded power over the intervals. companion_wh is what its
    pack gave: compute and radio through the converters."""
    if table.empty:
        return pd.DataFrame(columns=VEHICLE_COLUMNS)
    empty_at = {e["vehicle"]: e["t_sim_s"] for e in emptied}
    rows = []
    for vehicle, rows_of in table.groupby("vehicle", sort=False):
        wh = {f"{part}_wh": float((rows_of[f"{part}_w"] * rows_of["dt_s"]).sum() * WH_PER_J)
              for part in ("flight", "compute", "radio", "companion")}
        last = rows_of.iloc[-1]
        rows.append({"vehicle": vehicle, **wh, "total_wh": wh["flight_wh"] + wh["companion_wh"],
                     "flight_soc_end": float(last["flight_soc"]), "companion_soc_end": float(last["companion_soc"]),
                     "companion_empty_at_s": empty_at.get(vehicle)})
    return pd.DataFrame(rows, columns=VEHICLE_COLUMNS)


def summarize(vehicles: pd.DataFrame, summary: dict) -> dict:
    """The summary's energy figures: totals, and per complete iteration and per unit of training cost removed."""
    if vehicles.empty:
        return {}
    total_wh = float(vehicles["total_wh"].sum())
    companion_wh = float(vehicles["companion_wh"].sum())
    out = {"energy_wh": round(total_wh, 3), "companion_energy_wh": round(companion_wh, 3)}
    emptied = vehicles.dropna(subset=["companion_empty_at_s"])
    if not emptied.empty:
        out["companion_packs_empty"] = {v: f"at {t:g} s" for v, t in
                                        zip(emptied["vehicle"], emptied["companion_empty_at_s"], strict=True)}
    complete = summary.get("complete_iterations") or 0
    if complete:
        out["energy_per_iteration_j"] = round(total_wh * 3600.0 / complete, 2)
        out["companion_energy_per_iteration_j"] = round(companion_wh * 3600.0 / complete, 3)
    first, final = summary.get("first_cost"), summary.get("final_cost")
    if first is not None and final is not None and first > final:
        out["companion_energy_per_cost_drop_j"] = round(companion_wh * 3600.0 / (first - final), 3)
    return out
