from nac_onboard.mavlink.signing import SigningState, initial_timestamp
from sitl.mavlink.codec import FrameEncoder, mavlink, new_parser


def test_fast_encoder_matches_pymavlink_byte_for_byte():
    enc = FrameEncoder(7, 1)
    ref = mavlink.MAVLink(None, srcSystem=7, srcComponent=1)
    cases = [
        (mavlink.MAVLink_global_position_int_message, (1234, 473977420, 85455940, 510000, 10000, -5, 7, 0, 9000)),
        (mavlink.MAVLink_heartbeat_message, (2, 3, 217, 4, 4, 3)),
        (mavlink.MAVLink_attitude_message, (99, 0.1, -0.2, 3.0, 0.0, 0.0, 0.0)),
        (mavlink.MAVLink_heartbeat_message, (2, 3, 217, 4, 4, 3)),  # cached payload, new sequence number
    ]
    for cls, values in cases:
        ours = enc.fields(cls, *values)
        theirs = cls(*values).pack(ref)
        ref.seq = (ref.seq + 1) % 256
        assert ours == theirs


def test_encoded_frames_parse_back():
    enc = FrameEncoder(3)
    parser = new_parser()
    frame = enc.fields(mavlink.MAVLink_extended_sys_state_message, 0, 2)
    frame += enc.message(mavlink.MAVLink_statustext_message(6, b"hello"))
    msgs = parser.parse_buffer(frame)
    assert [m.get_type() for m in msgs] == ["EXTENDED_SYS_STATE", "STATUSTEXT"]
    assert msgs[0].landed_state == 2 and msgs[1].text == "hello"
    assert [m.get_seq() for m in msgs] == [0, 1]


def test_parser_survives_garbage():
    parser = new_parser()
    msgs = parser.parse_buffer(b"\xfd\x09garbage\x00\xfe\xff" * 20) or []
    assert all(m.get_type() == "BAD_DATA" for m in msgs)


def test_signed_frames_match_pymavlink_and_verify():
    key = bytes(range(32))
    signing = SigningState(key)
    signing.own = initial_timestamp() + 100_000  # a second ahead: the next timestamp is own + 1, known here
    enc = FrameEncoder(4, 1, signing=signing, link_id=0)
    ref = mavlink.MAVLink(None, srcSystem=4, srcComponent=1)
    ref.signing.secret_key, ref.signing.sign_outgoing, ref.signing.link_id = key, True, 0
    ref.signing.timestamp = signing.own + 1
    values = (2, 3, 217, 4, 4, 3)
    assert enc.fields(mavlink.MAVLink_heartbeat_message, *values) == mavlink.MAVLink_heartbeat_message(
        *values).pack(ref)
    checker = new_parser(SigningState(key))
    frame = enc.fields(mavlink.MAVLink_heartbeat_message, *values)
    frame += enc.message(mavlink.MAVLink_statustext_message(6, b"signed"))
    assert [m.get_type() for m in checker.parse_buffer(frame)] == ["HEARTBEAT", "STATUSTEXT"]
    unsigned = FrameEncoder(4).fields(mavlink.MAVLink_heartbeat_message, *values)
    assert [m.get_type() for m in new_parser(SigningState(key)).parse_buffer(unsigned)] == ["BAD_DATA"]
    wrong = FrameEncoder(4, signing=SigningState(bytes(32))).fields(mavlink.MAVLink_heartbeat_message, *values)
    assert [m.get_type() for m in new_parser(SigningState(key)).parse_buffer(wrong)] == ["BAD_DATA"]
