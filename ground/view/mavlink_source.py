"""Real vehicles watched over MAVLink, for the view during a flight: each vehicle's telemetry becomes the same
record an agent logs, so the page draws it as it draws a run. With the master agent's state feed, vehicles get
their fleet ids and roles (matched by sysid) and the feed's peers are drawn even when this link does not hear
them."""

from __future__ import annotations

import time

from ground.view.records import RunFollower
from nac_onboard.agent.state_feed import StateFeedError, fetch_state
from nac_onboard.mavlink.client import MavlinkClient
from nac_onboard.records import kinds

STREAM_HZ = 4  # what the view asks each autopilot for (REQUEST_DATA_STREAM), as MAVProxy does
FEED_PERIOD_S = 1.0


class MavlinkSource:
    def __init__(self, uris: list[str], feed: str | None = None):
        self.client = MavlinkClient(uris) if uris else None
        self.feed = feed
        self.names: dict[int, tuple[str, str]] = {}  # sysid -> (vehicle id, role), from the state feed
        self._last_boot_ms: dict[int, int] = {}
        self._asked: set[int] = set()
        self._next_feed_s = 0.0
        self._feed_failed = False

    def pump(self, follower: RunFollower) -> int:
        """Read what has arrived (without waiting) and add it to follower; how many frames that made."""
        added = 0
        if self.feed and time.monotonic() >= self._next_feed_s:
            self._next_feed_s = time.monotonic() + FEED_PERIOD_S
            added += self._read_feed(follower)
        if self.client is None:
            return added
        self.client.poll(0.0)
        now = time.time()
        for sysid, v in list(self.client.vehicles.items()):
            if sysid not in self._asked:
                self._asked.add(sysid)
                self.client.request_streams(STREAM_HZ, sysid)
            if v.lat_deg is None or v.time_boot_ms == self._last_boot_ms.get(sysid):
                continue
            self._last_boot_ms[sysid] = v.time_boot_ms
            vehicle, role = self.names.get(sysid, (f"sysid{sysid}", "?"))
            follower.vehicles.setdefault(vehicle, {})["role"] = role
            added += follower.add("agent", vehicle, {
                "t_s": now, "kind": kinds.TELEMETRY.name, "time_boot_ms": v.time_boot_ms, "lat_deg": v.lat_deg,
                "lon_deg": v.lon_deg, "alt_m": v.alt_m, "rel_alt_m": v.rel_alt_m, "yaw_deg": v.yaw_deg,
                "battery_pct": v.battery_pct, "mode": v.mode, "armed": v.armed,
                "mission_seq": v.mission_seq, "mission_total": v.mission_total}) is not None
        return added

    def _read_feed(self, follower: RunFollower) -> int:
        try:
            state = fetch_state(self.feed, timeout_s=0.2)
        except StateFeedError as err:
            if not self._feed_failed:
                follower.problems.append(f"state feed {self.feed}: {err}")
                self._feed_failed = True
            return 0
        added = 0
        heard_here = set(self.client.vehicles) if self.client else set()
        peers = state.get("peers") if isinstance(state, dict) else None
        entries = [state.get("self") if isinstance(state, dict) else None,
                   *(peers.values() if isinstance(peers, dict) else [])]
        for entry in entries:  # from the network: anything not shaped like the agent's answer is passed over
            if not isinstance(entry, dict):
                continue
            vehicle, role, sysid = entry.get("id"), entry.get("role", "?"), entry.get("sysid")
            if not isinstance(vehicle, str) or not vehicle.isprintable() or len(vehicle) > 32:
                continue
            if isinstance(sysid, int) and sysid > 0:
                self.names[sysid] = (vehicle, str(role))
            follower.vehicles.setdefault(vehicle, {})["role"] = str(role)
            if sysid in heard_here or entry.get("lost") or entry.get("lat_deg") is None:
                continue  # the link's own telemetry is fresher than the feed's
            added += follower.add("agent", vehicle, {"t_s": time.time(), "kind": kinds.TELEMETRY.name,
                                                     "lat_deg": entry["lat_deg"], "lon_deg": entry["lon_deg"],
                                                     "alt_m": entry.get("alt_m"),
                                                     "battery_pct": entry.get("battery_pct")}) is not None
        return added

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
