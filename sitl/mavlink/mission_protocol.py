"""Vehicle side of the MAVLink mission upload protocol as a pure state machine (times passed in, no I/O).

mavlink.io mission protocol: MISSION_COUNT -> the vehicle requests each item in order -> MISSION_ACK. The
vehicle re-requests the expected item after `item_timeout_s` without it (never faster: lossy radios turn eager
re-requests into storms), drops out-of-order items, and replaces the stored mission only once every item has
arrived and passed validation; any error or cancel leaves the old mission as it was. The spec asks for at least
five retries; like ArduPilot the vehicle keeps re-requesting until `idle_timeout_s` passes with no progress.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum

from missions.model import MavCmd, MissionItem, MissionType


class MissionResult(IntEnum):
    """MAV_MISSION_RESULT."""

    ACCEPTED = 0
    ERROR = 1
    UNSUPPORTED_FRAME = 2
    UNSUPPORTED = 3
    NO_SPACE = 4
    INVALID = 5
    INVALID_PARAM1 = 6
    INVALID_PARAM2 = 7
    INVALID_PARAM3 = 8
    INVALID_PARAM4 = 9
    INVALID_PARAM5_X = 10
    INVALID_PARAM6_Y = 11
    INVALID_PARAM7 = 12
    INVALID_SEQUENCE = 13
    DENIED = 14
    OPERATION_CANCELLED = 15


REACK_WINDOW_S = 30.0  # how long after completing an upload a repeated last item is answered with the ACK again

Partner = tuple  # (sysid, compid, channel id): whoever started the transfer


@dataclass
class Request:
    seq: int
    mission_type: int


@dataclass
class Ack:
    result: MissionResult
    mission_type: int


@dataclass
class Complete:
    mission_type: int
    items: list[MissionItem]


Action = Request | Ack | Complete


@dataclass
class _Upload:
    partner: Partner
    mission_type: int
    count: int
    items: list[MissionItem] = field(default_factory=list)
    last_request_s: float = 0.0
    last_progress_s: float = 0.0
    requests_sent: int = 0


class MissionReceiver:
    """One upload at a time per vehicle; `validate(item, type)` returns a MissionResult name or None."""

    def __init__(self, validate: Callable[[MissionItem, int], str | None], *, max_items: int = 10000,
                 item_timeout_s: float = 0.25, idle_timeout_s: float = 8.0):
        self.validate = validate
        self.max_items = max_items
        self.item_timeout_s = item_timeout_s
        self.idle_timeout_s = idle_timeout_s
        self.upload: _Upload | None = None
        # The last completed upload, so a GCS whose ACK was lost and who re-sends the last item is re-ACKed.
        self._finished: tuple[Partner, int, int, float] | None = None
        self.requests_sent_total = 0
        self.items_received_total = 0  # every MISSION_ITEM(_INT) that arrived, duplicates included

    @property
    def busy(self) -> bool:
        return self.upload is not None

    def _request(self, up: _Upload, now_s: float) -> Request:
        up.last_request_s = now_s
        up.requests_sent += 1
        self.requests_sent_total += 1
        return Request(len(up.items), up.mission_type)

    def on_count(self, partner: Partner, mission_type: int, count: int, now_s: float) -> list[Action]:
        try:
            MissionType(mission_type)
        except ValueError:
            return [Ack(MissionResult.UNSUPPORTED, mission_type)]
        up = self.upload
        if up is not None and up.partner != partner:
            return [Ack(MissionResult.DENIED, mission_type)]  # someone else's transfer is in progress
        if count < 0 or count > self.max_items:
            self.upload = None
            return [Ack(MissionResult.NO_SPACE, mission_type)]
        if count == 0:
            self.upload = None
            return [Complete(mission_type, []), Ack(MissionResult.ACCEPTED, mission_type)]
        # A repeated COUNT (our first request was lost) restarts the transfer.
        self.upload = _Upload(partner, mission_type, count, last_progress_s=now_s)
        self._finished = None
        return [self._request(self.upload, now_s)]

    def on_item(self, partner: Partner, item: MissionItem, now_s: float) -> list[Action]:
        self.items_received_total += 1
        up = self.upload
        if up is None:
            fin = self._finished
            if (fin is not None and fin[0] == partner and fin[1] == item.mission_type and item.seq == fin[2] - 1
                    and now_s - fin[3] < REACK_WINDOW_S):
                return [Ack(MissionResult.ACCEPTED, item.mission_type)]
            return []
        if partner != up.partner or item.mission_type != up.mission_type:
            return []
        expected = len(up.items)
        if item.seq != expected:
            # Drop it; re-request the expected item unless a request for it is still fresh.
            if now_s - up.last_request_s >= self.item_timeout_s:
                return [self._request(up, now_s)]
            return []
        error = self.validate(item, up.mission_type)
        if error is not None:
            self.upload = None
            return [Ack(MissionResult[error.removeprefix("MAV_MISSION_")], up.mission_type)]
        up.items.append(item)
        up.last_progress_s = now_s
        if len(up.items) < up.count:
            return [self._request(up, now_s)]
        jump_error = _check_jumps(up.items) if up.mission_type == MissionType.MISSION else None
        self.upload = None
        if jump_error is not None:
            return [Ack(jump_error, up.mission_type)]
        self._finished = (partner, up.mission_type, up.count, now_s)
        return [Complete(up.mission_type, up.items), Ack(MissionResult.ACCEPTED, up.mission_type)]

    def on_ack(self, partner: Partner) -> list[Action]:
        """A MISSION_ACK from the uploader mid-transfer means it gave up: cancel, keep the old mission."""
        if self.upload is not None and self.upload.partner == partner:
            self.upload = None
        return []

    def poll(self, now_s: float) -> list[Action]:
        up = self.upload
        if up is None:
            return []
        if now_s - up.last_progress_s >= self.idle_timeout_s:
            self.upload = None
            return [Ack(MissionResult.OPERATION_CANCELLED, up.mission_type)]
        if now_s - up.last_request_s >= self.item_timeout_s:
            return [self._request(up, now_s)]
        return []


def _check_jumps(items: list[MissionItem]) -> MissionResult | None:
    for item in items:
        if item.command == MavCmd.DO_JUMP and not 1 <= int(item.p1) < len(items):
            return MissionResult.INVALID_PARAM1
    return None
