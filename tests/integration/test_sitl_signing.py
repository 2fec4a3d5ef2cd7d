"""MAVLink 2 signing: with a key, the vehicle signs what it sends and refuses unsigned or wrongly signed input."""

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
