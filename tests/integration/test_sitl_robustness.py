"""Acceptance 5: garbage and nonsense do not stop the simulator; faults behave as on a real vehicle."""

import random

from missions.model import MavCmd
from sitl.mavlink.codec import mavlink
from tests.integration.gcs import M, take_off

INT_RANGES = {"int8_t": (-128, 127), "uint8_t": (0, 255), "int16_t": (-32768, 32767), "uint16_t": (0, 65535),
              "int32_t": (-2**31, 2**31 - 1), "uint32_t": (0, 2**32 - 1), "int64_t": (-2**63, 2**63 - 1),
              "uint64_t": (0, 2**64 - 1)}


def random_value(rng: random.Random, ftype: str, length: int):
    if ftype == "char":
        return bytes(rng.randrange(32, 127) for _ in range(rng.randrange(0, length + 1)))
    if ftype in ("float", "double"):
        scalar = lambda: rng.choice([0.0, -1.0, float("nan"), float("inf"), rng.uniform(-1e9, 1e9)])  # noqa: E731
    else:
        lo, hi = INT_RANGES[ftype.replace("_mavlink_version", "")]
        scalar = lambda: rng.randint(lo, hi)  # noqa: E731
    return [scalar() for _ in range(length)] if length else scalar()


def random_message(rng: random.Random):
    cls = rng.choice(list(mavlink.mavlink_map.values()))
    values = [random_value(rng, t, n) for t, n in zip(cls.fieldtypes, cls.array_lengths, strict=True)]
    msg = cls(*values)
    for name in ("target_system", "target_component"):  # aim most of them at the vehicle
        if name in cls.fieldnames and rng.random() < 0.8:
            setattr(msg, name, rng.choice([0, 1]))
    return msg


def vehicle_socket_address(sim, vehicle=0):
    return ("127.0.0.1", sim.protocols[vehicle].connections[0].sock.getsockname()[1])


def assert_still_answering(gcs):
    """A parameter read is answered. Asked again every 0.5 s, as a ground station does: a flood of datagrams
    can overflow the vehicle's socket buffer, and the kernel then drops whatever arrives, requests included."""
    for _ in range(10):
        gcs.conn.mav.param_request_read_send(1, 1, b"NAC_KP_XY", -1)
        if gcs.recv("PARAM_VALUE", 0.5, lambda m: m.param_id == "NAC_KP_XY") is not None:
            break
    else:
        raise AssertionError("the vehicle stopped answering parameter reads")
    assert gcs.recv("HEARTBEAT", 5.0) is not None


def test_garbage_and_nonsense_do_not_stop_the_vehicles(start_sitl, gcs_for):
    sim = start_sitl(vehicles=2, speedup=5.0, tcp_base_port=0)
    gcs = gcs_for(sim, 0)
    target = vehicle_socket_address(sim)
    rng = random.Random(42)
    # Sent from the ground station's own socket: the link is connected to it, so only it is heard (a radio
    # that garbles frames, a client with a bug); anyone else's datagrams never reach the vehicle.
    sender = gcs.conn.port
    for _batch in range(10):
        for _ in range(1000):
            size = rng.randrange(1, 300)
            data = bytes(rng.getrandbits(8) for _ in range(size))
            if rng.random() < 0.3:  # start like a MAVLink frame so the parser goes deeper
                data = bytes([rng.choice([0xFD, 0xFE])]) + data
            sender.sendto(data, target)
        assert_still_answering(gcs)  # each batch processed before the next: the vehicle keeps up

    encoder = mavlink.MAVLink(None, srcSystem=200, srcComponent=1)
    for _batch in range(10):
        for _ in range(100):
            msg = random_message(rng)
            try:
                frame = msg.pack(encoder)
            except Exception:
                continue  # values that pymavlink itself cannot encode are not well-formed
            encoder.seq = (encoder.seq + 1) % 256
            sender.sendto(frame, target)
        assert_still_answering(gcs)
    assert sim.stats["bad_frames"] > 0
    assert sim.stats["handler_errors"] == 0, "a handler raised on a well-formed message"
    assert sim._thread.is_alive()
    # The other vehicle never heard any of it and is as it was.
    assert not sim.truth(1)["armed"] and sim.truth(1)["on_ground"]


def test_truncated_frames_and_wrong_sysid_commands(start_sitl, gcs_for):
    sim = start_sitl(speedup=5.0)
    gcs = gcs_for(sim)
    target = vehicle_socket_address(sim)
    encoder = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    frame = mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(encoder)
    for cut in range(1, len(frame)):  # from the link's own client: nobody else is heard
        gcs.conn.port.sendto(frame[:cut], target)
    assert_still_answering(gcs)
    assert not sim.truth(0)["armed"]  # no truncated copy was taken for a command


def test_link_down_then_up(start_sitl, gcs_for):
    sim = start_sitl(speedup=5.0)
    gcs = gcs_for(sim)
    sim.set_link_down(0, "ground", True)
    assert gcs.recv("HEARTBEAT", 2.0) is None
    sim.set_link_down(0, "ground", False)
    assert gcs.recv("HEARTBEAT", 3.0) is not None


def test_gps_loss_in_flight_makes_the_vehicle_land(start_sitl, gcs_for):
    sim = start_sitl(speedup=10.0)
    gcs = gcs_for(sim)
    take_off(gcs, 10)
    sim.set_gps_lost(0, True)
    raw = gcs.recv("GPS_RAW_INT", 3.0, lambda m: m.fix_type < 2)
    assert raw is not None and raw.satellites_visible == 0
    assert gcs.recv("HEARTBEAT", 3.0, lambda m: m.custom_mode == 9) is not None  # LAND
    assert gcs.recv("EXTENDED_SYS_STATE", 40.0, lambda m: m.landed_state == M.MAV_LANDED_STATE_ON_GROUND)
    assert gcs.command(MavCmd.COMPONENT_ARM_DISARM, 1) in (M.MAV_RESULT_ACCEPTED, M.MAV_RESULT_FAILED)
    sim.set_gps_lost(0, False)


def test_low_battery_triggers_return_to_launch(start_sitl, gcs_for):
    sim = start_sitl(speedup=10.0)
    gcs = gcs_for(sim)
    take_off(gcs, 5)
    gcs.conn.mav.param_set_send(1, 1, b"SIM_BATT_PCT", 10, M.MAV_PARAM_TYPE_REAL32)  # the fault as a parameter
    assert gcs.recv("HEARTBEAT", 3.0, lambda m: m.custom_mode == 6 and m.system_status == M.MAV_STATE_CRITICAL)
    status = gcs.recv("SYS_STATUS", 3.0)
    assert status.battery_remaining <= 10
    assert gcs.recv("STATUSTEXT", 60.0, lambda m: m.text == "Landed") is not None
    truth = sim.truth(0)
    assert abs(truth["pos_m"][0]) < 2.5 and abs(truth["pos_m"][1]) < 2.5


def test_only_the_links_own_client_can_command_a_vehicle(start_sitl, gcs_for):
    """The SITL's UDP links once took commands from any sender; now each is connected to its one client."""
    from pymavlink import mavutil

    from missions.model import MavCmd

    sim = start_sitl()
    gcs = gcs_for(sim, 0)
    vehicle_socket = next(iter(gcs.conn.clients))  # where the vehicle's ground link sends from
    intruder = mavutil.mavlink_connection(f"udpout:{vehicle_socket[0]}:{vehicle_socket[1]}", source_system=66)
    try:
        for _ in range(5):
            intruder.mav.command_long_send(1, 1, MavCmd.COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        # a barrier on the same link: the client's own command is answered after the intruder's were sent
        assert gcs.command(MavCmd.REQUEST_MESSAGE, 0) is not None
        assert not sim.truth(0)["armed"]
        assert gcs.command(MavCmd.COMPONENT_ARM_DISARM, 1) == 0 and sim.truth(0)["armed"]
    finally:
        intruder.close()
    assert all(ends["tcp"].startswith("127.0.0.1:") for ends in sim.endpoints if "tcp" in ends)
