"""The agent's link to its autopilot: open it, notice when it goes quiet (link_lost after link_timeout_s without
a heartbeat) and when it comes back (link_restored, with the outage), reopen it where that helps (serial, TCP).

Events go to the agent's log; the decoded messages go back to the agent, which logs and routes them.

The link has one peer on every transport: a listening one (udpin:, tcpin:) takes frames only from autopilot.peer,
or else from the first sender that speaks valid MAVLink, then locked until the link is lost (no heartbeat for
link_timeout_s: a restarted autopilot may speak from another port) (nac_onboard/mavlink/client.py OnePeerUdp,
OnePeerTcpIn); everyone else is refused before decoding, counted, and logged at most every REFUSALS_LOGGED_EVERY_S.
"""

from __future__ import annotations

from collections.abc import Callable

from nac_onboard.address import is_loopback, parse_host_port
from nac_onboard.agent.config import AutopilotSection
from nac_onboard.errors import BadInput
from nac_onboard.flight_log import JsonlLog
from nac_onboard.mavlink.client import CLIENT_MESSAGES, LinkError, MavlinkClient, TelemetryState, parse_peer
from nac_onboard.mavlink.dialect import M
from nac_onboard.mavlink.signing import state_path
from nac_onboard.records import kinds

OPEN_FAILURES_LOGGED_EVERY = 30  # a long outage logs its first failure and then one in this many
REFUSALS_LOGGED_EVERY_S = 10.0  # refused senders: one record at most this often, with the count since the last


class AutopilotLink:
    def __init__(self, config: AutopilotSection, own_sysid: int, sysid: int | None, signing_key: bytes | None,
                 log: JsonlLog, on_status: Callable[[str], None], tap: Callable[[bytes], None] | None = None):
        self.config = config
        self.link_timeout_s = config.link_timeout_s  # wall; the agent stretches it on a slowed run's clock
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
        self.one_peer = parse_peer(config.peer, "autopilot.peer")
        self.refused = 0  # from others than the peer, over every opening of the link
        self._refused_logged, self._last_refusal_log_s = 0, -1e9
        self._link_refused = 0  # what the open link's counter showed at the last read
        self._peer_logged = ""
        self._warn_if_open_to_all()

    def _warn_if_open_to_all(self) -> None:
        scheme, _, rest = self.config.uri.partition(":")
        if scheme not in ("udpin", "tcpin") or self.config.peer:
            return
        try:
            host, _ = parse_host_port(rest, "autopilot.uri", allow_port_zero=True)
        except BadInput:
            return
        if not is_loopback(host):
            self.log.write(kinds.WARNING, text=f"the autopilot link {self.config.uri} listens beyond loopback with no "
                           "autopilot.peer: the first sender that speaks MAVLink there becomes the autopilot; set "
                           "autopilot.peer to its address (docs/security.md)")

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
                                        mav_type=M.MAV_TYPE_ONBOARD_CONTROLLER, decode_only=CLIENT_MESSAGES,
                                        one_peer=self.one_peer)
        except LinkError as err:
            self.open_failures += 1
            if self.open_failures == 1 or self.open_failures % OPEN_FAILURES_LOGGED_EVERY == 0:
                self.log.write(kinds.LINK_OPEN_FAILED, uri=self.config.uri, error=str(err), attempts=self.open_failures)
            return
        if self.open_failures:
            self.log.write(kinds.LINK_OPENED, uri=self.config.uri, after_attempts=self.open_failures + 1)
        self.open_failures = 0
        self._link_refused = 0
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
            self._note_refusals(now_s)
            self.client.close()
            self.client = None
            return []
        self._note_refusals(now_s)
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

    def _note_refusals(self, now_s: float) -> None:
        """Count what the link refused; log the peer once taken, and the refusals at most every
        REFUSALS_LOGGED_EVERY_S (a flood is one record per period, not one per datagram)."""
        link = self.client.links[0]
        if link.refused != self._link_refused:
            self.refused += link.refused - self._link_refused
            self._link_refused = link.refused
        peer = link.peer
        if peer and peer != self._peer_logged:
            self._peer_logged = peer
            self.log.write(kinds.AUTOPILOT_PEER, uri=self.config.uri, peer=peer, configured=self.config.peer)
        if self.refused > self._refused_logged and now_s - self._last_refusal_log_s >= REFUSALS_LOGGED_EVERY_S:
            sender = link.conn.last_refused_from
            self.log.write(kinds.AUTOPILOT_REFUSED, refused_since_last_record=self.refused - self._refused_logged,
                           last_sender=f"{sender[0]}:{sender[1]}" if sender else "", peer=peer)
            self._refused_logged, self._last_refusal_log_s = self.refused, now_s

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
            if silent_s > self.link_timeout_s:
                self._mark_lost(now_s - silent_s, "silent", silent_s=round(silent_s, 3))
        reopenable = not a.uri.startswith("udpin:")  # a listening UDP socket needs no reopening
        if not self.up and now_s - self.last_open_attempt_s >= a.reconnect_s:
            if self.client is None:
                self.open(now_s)
            elif reopenable and self.ever_up:
                self.last_open_attempt_s = now_s
                try:
                    self.client.reopen(0)
                    self._link_refused = 0
                    self._tap()
                except LinkError:
                    self.client.close()
                    self.client = None

    def _mark_lost(self, since_s: float, why: str, **extra) -> None:
        if not self.up:
            return
        self.up = False
        self.lost_since_s = since_s
        if self.client is not None:  # a silent peer's address is not kept: the autopilot may restart on another port
            self.client.links[0].release_peer()
        self.log.write(kinds.LINK_LOST, sysid=self.sysid, why=why, **extra)
        self.on_status(f"autopilot link lost ({why}); retrying")

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
