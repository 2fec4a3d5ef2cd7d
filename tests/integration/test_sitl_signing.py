"""MAVLink 2 signing: with a key, the vehicle signs what it sends and refuses unsigned or wrongly signed input."""

import struct

from missions.model import MavCmd
from nac_onboard.mavlink.signing import load_signing_key
from tests.integration.gcs import Gcs, M


def test_signed_vehicle_answers_only_signed_commands(start_sitl, tmp_path):
    key_file = tmp_path / "fleet.key"
    key_file.write_text("correct horse battery staple\n")
    key = load_signing_key(key_file)
    sim = start_sitl(speedup=5.0, signing_key=key)
    port = sim.config.gcs_base_port

    unsigned = Gcs(port)
    try:
        hb = unsigned.wait_heartbeat()
        assert hb.get_header().incompat_flags & 1  # everything the vehicle sends carries a signature
        unsigned.conn.mav.command_long_send(1, 1, MavCmd.COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert unsigned.recv("COMMAND_ACK", 1.5) is None
        assert not sim.truth(0)["armed"]
    finally:
        unsigned.close()

    wrong = Gcs(port)
    try:
        wrong.wait_heartbeat()
        wrong.conn.setup_signing(bytes(32), sign_outgoing=True)
        wrong.conn.mav.command_long_send(1, 1, MavCmd.COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert wrong.recv("COMMAND_ACK", 1.5) is None
    finally:
        wrong.close()

    signed = Gcs(port)
    try:
        signed.conn.setup_signing(key, sign_outgoing=True)
        signed.wait_heartbeat()
        assert signed.command(MavCmd.COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert sim.truth(0)["armed"]
    finally:
        signed.close()
    assert sim.stats["bad_frames"] >= 2


def ground_socket(sim) -> tuple[str, int]:
    """Where vehicle 1's ground link listens (its socket is connected to the ground station's port)."""
    return sim.protocols[0].connections[0].sock.getsockname()


def signed_frame(key: bytes, msg, timestamp: int, link_id: int = 0, src=(255, 190)) -> bytes:
    """A frame signed as a ground station would sign it, with the timestamp given."""
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    mav = dialect.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    mav.signing.secret_key, mav.signing.sign_outgoing = key, True
    mav.signing.link_id, mav.signing.timestamp = link_id, timestamp
    return bytes(msg.pack(mav))


def arm(value: int):
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    return dialect.MAVLink_command_long_message(1, 1, MavCmd.COMPONENT_ARM_DISARM, 0, value, 0, 0, 0, 0, 0, 0)


def test_a_forged_far_future_frame_does_not_lock_the_ground_station_out(start_sitl):
    """pymavlink stores a frame's timestamp before checking its signature: one forged frame dated 2^48-1 once made
    the vehicle refuse every later frame of the real ground station on that stream."""
    from nac_onboard.mavlink.signing import initial_timestamp

    key = bytes(range(32))
    sim = start_sitl(speedup=5.0, signing_key=key)
    gcs = Gcs(sim.config.gcs_base_port)
    try:
        gcs.conn.setup_signing(key, sign_outgoing=True)
        gcs.wait_heartbeat()
        target = ground_socket(sim)
        forged = bytearray(signed_frame(bytes(32), arm(1), 2 ** 48 - 1, src=(255, 190)))  # wrong key, far future
        gcs.conn.port.sendto(bytes(forged), target)
        ahead = signed_frame(key, arm(1), initial_timestamp() + 3600 * 100_000)  # right key, an hour ahead
        gcs.conn.port.sendto(ahead, target)
        assert gcs.command(MavCmd.REQUEST_MESSAGE, 0) is not None  # a barrier on the same link
        assert not sim.truth(0)["armed"], "a frame dated an hour ahead is refused"
        assert gcs.command(MavCmd.COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED and sim.truth(0)["armed"]
        assert sim.signing.refused["signature"] >= 1 and sim.signing.refused["ahead"] == 1
    finally:
        gcs.close()


def test_a_captured_signed_command_does_not_replay_after_the_vehicle_restarts(start_sitl, tmp_path):
    from nac_onboard.mavlink.signing import initial_timestamp

    key = bytes(range(32))
    sim = start_sitl(speedup=5.0, signing_key=key, signing_state_file=str(tmp_path / "key.timestamps"))
    config = sim.config
    gcs = Gcs(config.gcs_base_port)
    try:
        gcs.conn.setup_signing(key, sign_outgoing=True)
        gcs.wait_heartbeat()
        captured = signed_frame(key, arm(1), initial_timestamp(), src=(255, 190))
        gcs.conn.port.sendto(captured, ground_socket(sim))
        assert gcs.recv("COMMAND_ACK", 3.0) is not None and sim.truth(0)["armed"]
        sim.stop()
        restarted = start_sitl(config=config)  # the same ports, the same state file
        gcs.wait_heartbeat()
        gcs.conn.port.sendto(captured, ground_socket(restarted))
        assert gcs.command(MavCmd.REQUEST_MESSAGE, 0) is not None  # a barrier on the same link
        assert not restarted.truth(0)["armed"], "the captured ARM was refused as a replay"
        assert restarted.signing.refused["replayed"] >= 1
    finally:
        gcs.close()


def test_the_vehicles_signing_timestamps_follow_the_clock(start_sitl):
    """They once advanced one tick a frame, falling ~1 s behind a second; a ground station started a minute
    later then refused the vehicle as a stream from the past ("the signing key differs")."""
    from nac_onboard.mavlink.signing import initial_timestamp

    key = bytes(range(32))
    sim = start_sitl(speedup=5.0, signing_key=key)
    gcs = Gcs(sim.config.gcs_base_port)
    try:
        gcs.conn.setup_signing(key, sign_outgoing=True)
        for _ in range(3):
            hb = gcs.wait_heartbeat()
        low, high = struct.unpack("<IH", hb.get_msgbuf()[-12:-6])
        assert abs((low + (high << 32)) - initial_timestamp()) < 2 * 100_000, "within 2 s of the clock"
    finally:
        gcs.close()
