"""The agent's link to its autopilot: open it, notice when it goes quiet (link_lost after link_timeout_s without
a heartbeat) and when it comes back (link_restored, with the outage), reopen it where that helps (serial, TCP).

Events go to the agent's log; the decoded messages go back to the agent, which logs and routes them.
"""

from __future__ import annotations

from collections.abc import Callable

from nac_onboard.agent.config import AutopilotSection
from nac_onboard.flight_log import JsonlLog
from nac_onboard.mavlink.client import CLIENT_MESSAGES, LinkError, MavlinkClient, TelemetryState
from nac_onboard.mavlink.dialect import M
from nac_onboard.mavlink.signing import state_path
from nac_onboard.records import kinds

OPEN_FAILURES_LOGGED_EVERY = 30  # a long outage logs its first failure and then one in this many


class AutopilotLink:
    def __init__(self, config: AutopilotSection, own_sysid: int, sysid: int | None, signing_key: bytes | None,
                 log: JsonlLog, on_status: Callable[[str], None], tap: Callable[[bytes], None] | None = None):
        self.config = config
        self.own_sysid = own_sysid  # what the companion sends as (the vehicle's sysid, as a Pixhawk's companion)
        self.sysid = sysid  # the autopilot's; None: the first autopilot heard
        self.signing_key = signing_key
        self.log, self.on_status, self.tap = log, on_status, tap
        self.client: MavlinkClient | None = None
        self.up = False
        self.ever_up = False
        self.lost_since_s = 0.0
        self.last_open_attempt_s = -1e9
        self.open_failures = 0

    # ---- what the agent reads ---------------------------------------------------------------------------
    def readers(self) -> list:
        return list(self.client.links) if self.client is not None else []

    def vehicle(self) -> TelemetryState | None:
        """The autopilot's telemetry state, once it has spoken."""
        if self.client is None or self.sysid is None:
            return None
        return self.client.vehicles.get(self.sysid)

    def write_frame(self, frame: bytes) -> None:
        """Pass a routed frame to the autopilot (dropped while there is no link)."""
        if self.client is not None:
            try:
                self.client.links[0].write_frame(frame)
            except OSError:
                pass

    def request_streams(self, rate_hz: float) -> None:
        if self.client is not None:
            self.client.request_streams(rate_hz, sysid=self.sysid)

    # ---- the link's life ------------------------------------------------------------------------------------
    def open(self, now_s: float) -> None:
        self.last_open_attempt_s = now_s
        try:
            self.client = MavlinkClient(self.config.uri, sysid=self.sysid, signing_key=self.signing_key,
                                        signing_state_file=str(state_path(self.config.signing_key_file))
                                        if self.signing_key else None,
                                        source_system=self.own_sysid, source_component=M.MAV_COMP_ID_ONBOARD_COMPUTER,
                                        mav_type=M.MAV_TYPE_ONBOARD_CONTROLLER, decode_only=CLIENT_MESSAGES)
        except LinkError as err:
            self.open_failures += 1
            if self.open_failures == 1 or self.open_failures % OPEN_FAILURES_LOGGED_EVERY == 0:
                self.log.write(kinds.LINK_OPEN_FAILED, uri=self.config.uri, error=str(err), attempts=self.open_failures)
            return
        if self.open_failures:
            self.log.write(kinds.LINK_OPENED, uri=self.config.uri, after_attempts=self.open_failures + 1)
        self.open_failures = 0
        self._tap()

    def _tap(self) -> None:
        if self.tap is not None:
            self.client.tap_sent(self.tap)

    def read(self, now_s: float) -> list:
        """Every message that arrived (for logging and routing); notes the autopilot's heartbeats."""
        if self.client is None:
            return []
        try:
            messages = self.client.poll(0.0)
        except (OSError, LinkError) as err:  # a serial adapter unplugged, a TCP peer gone
            self.log.write(kinds.LINK_ERROR, uri=self.config.uri, error=str(err))
            self._mark_lost(now_s, "error")
            self.client.close()
            self.client = None
            return []
        if self.sysid is None:
            autopilots = [s for s, v in self.client.vehicles.items() if v.autopilot != M.MAV_AUTOPILOT_INVALID]
            if autopilots:
                self.sysid = self.client.sysid = autopilots[0]
        if not self.up:
            for msg in messages:
                if (msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == self.sysid
                        and msg.get_srcComponent() == M.MAV_COMP_ID_AUTOPILOT1):
                    self._came_up(msg, now_s)
                    break
        return messages

    def _came_up(self, heartbeat, now_s: float) -> None:
        self.up = True
        if self.ever_up:
            self.log.write(kinds.LINK_RESTORED, sysid=self.sysid, outage_s=round(now_s - self.lost_since_s, 3))
        else:
            self.log.write(kinds.LINK_UP, sysid=self.sysid, autopilot=heartbeat.autopilot, vehicle_type=heartbeat.type,
                           mavlink_version=heartbeat.mavlink_version)
        self.ever_up = True
        self.on_status(f"autopilot {self.sysid} linked")
        if self.config.stream_hz > 0:
            self.request_streams(self.config.stream_hz)

    def check(self, now_s: float) -> None:
        """Call every loop: a silent link is lost; a lost one is reopened every reconnect_s."""
        a = self.config
        vehicle = self.vehicle()
        if self.up and vehicle is not None:
            silent_s = vehicle.link_age_s(now_s)
            if silent_s > a.link_timeout_s:
                self._mark_lost(now_s - silent_s, "silent", silent_s=round(silent_s, 3))
        reopenable = not a.uri.startswith("udpin:")  # a listening UDP socket needs no reopening
        if not self.up and now_s - self.last_open_attempt_s >= a.reconnect_s:
            if self.client is None:
                self.open(now_s)
            elif reopenable and self.ever_up:
                self.last_open_attempt_s = now_s
                try:
                    self.client.reopen(0)
                    self._tap()
                except LinkError:
                    self.client.close()
                    self.client = None

    def _mark_lost(self, since_s: float, why: str, **extra) -> None:
        if not self.up:
            return
        self.up = False
        self.lost_since_s = since_s
        self.log.write(kinds.LINK_LOST, sysid=self.sysid, why=why, **extra)
        self.on_status(f"autopilot link lost ({why}); retrying")

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
