"""MAVLink 2 signing as the spec asks: the signature before any state changes, no timestamp far ahead of the
clock, and timestamps that survive a restart."""

from pymavlink.dialects.v20 import ardupilotmega as dialect

from nac_onboard.mavlink.signing import MAX_AHEAD, SigningState, initial_timestamp

KEY = bytes(range(32))


def frame(key: bytes, timestamp: int) -> bytearray:
    mav = dialect.MAVLink(None, srcSystem=255, srcComponent=190)
    mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.timestamp = key, True, timestamp
    return bytearray(dialect.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(mav))


def test_a_forged_frame_changes_nothing_and_the_real_stream_goes_on():
    state = SigningState(KEY)
    now = initial_timestamp()
    assert not state.accept(frame(bytes(32), 2 ** 48 - 1), 255, 190), "wrong key"
    assert state.streams == {} and state.refused["signature"] == 1
    assert not state.accept(frame(KEY, now + MAX_AHEAD + 100_000), 255, 190), "right key, too far ahead"
    assert state.accept(frame(KEY, now), 255, 190) and state.accept(frame(KEY, now + 1), 255, 190)
    assert not state.accept(frame(KEY, now + 1), 255, 190), "the same timestamp twice is a replay"


def test_timestamps_survive_a_restart(tmp_path):
    path = tmp_path / "key.timestamps"
    first = SigningState(KEY, path)
    seen = frame(KEY, initial_timestamp())
    assert first.accept(seen, 255, 190)
    sent = first.next_timestamp()
    first.save(force=True)
    again = SigningState(KEY, path)
    assert not again.accept(seen, 255, 190), "a frame accepted before the restart is a replay after it"
    assert again.next_timestamp() > sent, "never a timestamp used before"
