"""The vehicle table of `nac-ground status` and `monitor` (pure: states in, text out)."""

from __future__ import annotations

import math

COLUMNS = ("SYSID", "MODE", "ARMED", "LAT", "LON", "ALT m", "GS m/s", "BATT %", "ITEM", "LINK s")


def _num(value: float, fmt: str) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, fmt)


def vehicle_rows(vehicles: dict, now_s: float) -> list[tuple[str, ...]]:
    rows = []
    for sysid in sorted(vehicles):
        v = vehicles[sysid]
        rows.append((
            str(sysid), v.mode, "yes" if v.armed else "no", _num(v.lat_deg, ".7f"), _num(v.lon_deg, ".7f"),
            _num(v.rel_alt_m, ".1f"), _num(v.ground_speed_mps, ".1f"),
            "-" if v.battery_pct is None else str(v.battery_pct), f"{v.mission_seq}/{v.mission_total}",
            _num(v.link_age_s(now_s), ".1f"),
        ))
    return rows


def render(vehicles: dict, now_s: float) -> str:
    rows = [COLUMNS, *vehicle_rows(vehicles, now_s)]
    widths = [max(len(row[k]) for row in rows) for k in range(len(COLUMNS))]
    numeric_from = 3  # text columns left-aligned, numbers right-aligned
    lines = ["  ".join(cell.rjust(w) if k >= numeric_from else cell.ljust(w)
                       for k, (cell, w) in enumerate(zip(row, widths, strict=True))) for row in rows]
    if not vehicles:
        lines.append("(no vehicle heard)")
    return "\n".join(line.rstrip() for line in lines)
