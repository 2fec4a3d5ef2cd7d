import pytest

from nac_onboard.mavlink_client import LinkError, mavutil_device


def test_uris_map_to_pymavlink_devices():
    assert mavutil_device("udpin:0.0.0.0:14550") == ("udpin:0.0.0.0:14550", {})
    assert mavutil_device("tcp:127.0.0.1:5760") == ("tcp:127.0.0.1:5760", {})
    assert mavutil_device("serial:/dev/ttyTHS2:921600") == ("/dev/ttyTHS2", {"baud": 921600})


@pytest.mark.parametrize("uri", ["udp:14550", "serial:/dev/ttyUSB0", "http://x", "tcp:host:port"])
def test_bad_uris_are_explained(uri):
    with pytest.raises(LinkError, match="expected udpin:HOST:PORT"):
        mavutil_device(uri)
