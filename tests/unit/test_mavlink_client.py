import pytest

from nac_onboard.errors import BadInput
from nac_onboard.mavlink.client import mavutil_device


def test_uris_map_to_pymavlink_devices():
    assert mavutil_device("udpin:0.0.0.0:14550") == ("udpin:0.0.0.0:14550", {})
    assert mavutil_device("tcp:127.0.0.1:5760") == ("tcp:127.0.0.1:5760", {"retries": 0})
    assert mavutil_device("serial:/dev/ttyTHS2:921600") == ("/dev/ttyTHS2", {"baud": 921600})


@pytest.mark.parametrize("uri", ["udp:14550", "serial:/dev/ttyUSB0", "http://x", "tcp:host:port"])
def test_bad_uris_are_explained(uri):
    with pytest.raises(BadInput, match="expected udpin:HOST:PORT"):
        mavutil_device(uri)


def test_frames_are_split_without_decoding_and_garbage_is_skipped():
    from pymavlink.dialects.v20 import all as dialect

    from nac_onboard.mavlink.frames import frame_msgid, frame_source, split_frames

    mav = dialect.MAVLink(None, srcSystem=7, srcComponent=1)
    a = mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav)
    b = mav.global_position_int_encode(1, 2, 3, 4, 5, 6, 7, 8, 9).pack(mav)
    frames, used, skipped = split_frames(b"\x00junk" + a + b"\x01" + b + b[:5])
    assert frames == [bytes(a), bytes(b)] and skipped == 6
    assert used == 5 + len(a) + 1 + len(b), "a frame cut off at the end waits for the rest"
    assert [frame_msgid(f) for f in frames] == [0, 33] and frame_source(frames[1]) == (7, 1)
