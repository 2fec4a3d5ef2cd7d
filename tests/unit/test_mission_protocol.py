from missions.firmware import arducopter_refusal as validate_item
from missions.model import MavCmd, MissionItem
from sitl.mavlink.mission_protocol import Ack, Complete, MissionReceiver, MissionResult, Request

GCS = (255, 190, 1)
OTHER = (254, 1, 2)


def items(n):
    return [MissionItem(k, MavCmd.NAV_WAYPOINT, lat_deg=47.0, lon_deg=8.0, alt_m=10) for k in range(n)]


def test_happy_upload_requests_each_item_once_and_completes():
    rx = MissionReceiver(validate_item)
    assert rx.on_count(GCS, 0, 3, 0.0) == [Request(0, 0)]
    assert rx.on_item(GCS, items(3)[0], 0.01) == [Request(1, 0)]
    assert rx.on_item(GCS, items(3)[1], 0.02) == [Request(2, 0)]
    actions = rx.on_item(GCS, items(3)[2], 0.03)
    assert isinstance(actions[0], Complete) and len(actions[0].items) == 3
    assert actions[1] == Ack(MissionResult.ACCEPTED, 0)
    assert not rx.busy and rx.requests_sent_total == 3


def test_rerequests_are_paced_by_the_item_timeout():
    rx = MissionReceiver(validate_item, item_timeout_s=0.25)
    rx.on_count(GCS, 0, 3, 0.0)
    assert rx.poll(0.1) == []
    assert rx.poll(0.26) == [Request(0, 0)]
    # an out-of-order item right after a request does not trigger a second request (no storms)
    assert rx.on_item(GCS, items(3)[2], 0.3) == []
    assert rx.on_item(GCS, items(3)[2], 0.6) == [Request(0, 0)]


def test_gives_up_after_idle_timeout_and_keeps_nothing():
    rx = MissionReceiver(validate_item, idle_timeout_s=8.0)
    rx.on_count(GCS, 0, 3, 0.0)
    rx.on_item(GCS, items(3)[0], 0.1)
    t, retries = 0.1, 0
    while rx.busy:
        t += 0.25
        actions = rx.poll(t)
        retries += sum(isinstance(a, Request) for a in actions)
    assert actions == [Ack(MissionResult.OPERATION_CANCELLED, 0)]
    assert retries >= 5 and 7.9 <= t - 0.1 <= 8.3


def test_errors_and_cancel_never_complete():
    rx = MissionReceiver(validate_item)
    rx.on_count(GCS, 0, 3, 0.0)
    bad = MissionItem(1, 31337, lat_deg=1, lon_deg=1)
    rx.on_item(GCS, items(3)[0], 0.1)
    assert rx.on_item(GCS, bad, 0.2) == [Ack(MissionResult.UNSUPPORTED, 0)]
    rx.on_count(GCS, 0, 3, 1.0)
    rx.on_ack(GCS)
    assert not rx.busy
    rx.on_count(GCS, 0, 2, 2.0)
    assert rx.on_item(GCS, MissionItem(0, 16), 2.1) == [Request(1, 0)]
    assert rx.on_item(GCS, MissionItem(1, 16, lat_deg=91.0), 2.2) == [Ack(MissionResult.INVALID_PARAM5_X, 0)]


def test_bad_jump_target_is_refused_at_the_end():
    rx = MissionReceiver(validate_item)
    rx.on_count(GCS, 0, 2, 0.0)
    rx.on_item(GCS, items(1)[0], 0.1)
    assert rx.on_item(GCS, MissionItem(1, MavCmd.DO_JUMP, p1=7, p2=1), 0.2) == [Ack(MissionResult.INVALID_PARAM1, 0)]


def test_second_uploader_is_denied_and_count_zero_clears():
    rx = MissionReceiver(validate_item)
    rx.on_count(GCS, 0, 3, 0.0)
    assert rx.on_count(OTHER, 0, 3, 0.1) == [Ack(MissionResult.DENIED, 0)]
    assert rx.on_item(OTHER, items(3)[0], 0.2) == []
    rx.on_ack(GCS)
    assert rx.on_count(GCS, 0, 0, 1.0) == [Complete(0, []), Ack(MissionResult.ACCEPTED, 0)]
    assert rx.on_count(GCS, 9, 1, 1.0) == [Ack(MissionResult.UNSUPPORTED, 9)]
    assert rx.on_count(GCS, 0, 10**6, 1.0) == [Ack(MissionResult.NO_SPACE, 0)]


def test_lost_final_ack_is_repeated_when_the_last_item_comes_again():
    rx = MissionReceiver(validate_item)
    rx.on_count(GCS, 0, 1, 0.0)
    assert rx.on_item(GCS, items(1)[0], 0.1)[-1] == Ack(MissionResult.ACCEPTED, 0)
    assert rx.on_item(GCS, items(1)[0], 1.6) == [Ack(MissionResult.ACCEPTED, 0)]
