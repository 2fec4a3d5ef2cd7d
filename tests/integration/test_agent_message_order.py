"""No order of valid autopilot messages crashes the agent: EXTENDED_SYS_STATE or MISSION_CURRENT before the first
HEARTBEAT once did (KeyError), and under systemd that is a crash loop. The agent runs in-process here and reads
shuffled streams from a pymavlink autopilot stand-in on its companion port."""

import select
import time

from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink import mavutil

from nac_onboard.agent.config import parse_agent_config
from nac_onboard.agent.daemon import Agent
from nac_onboard.mavlink.dialect import M
from nac_onboard.tomlfile import read_toml
from tests.conftest import free_port
from tests.integration.agents import agent_toml

ORDERS = 25
KINDS = ["heartbeat", "extended_sys_state", "mission_current", "global_position_int", "statustext",
         "mission_item_reached", "sys_status", "attitude"]


def send(mav, kind: str) -> None:
    if kind == "heartbeat":
        mav.heartbeat_send(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, M.MAV_STATE_STANDBY)
    elif kind == "extended_sys_state":
        mav.extended_sys_state_send(0, M.MAV_LANDED_STATE_ON_GROUND)
    elif kind == "mission_current":
        mav.mission_current_send(1, 3, M.MISSION_STATE_ACTIVE, 1)
    elif kind == "global_position_int":
        mav.global_position_int_send(1000, 473977420, 85455940, 488000, 0, 0, 0, 0, 0)
    elif kind == "statustext":
        mav.statustext_send(M.MAV_SEVERITY_INFO, b"hello")
    elif kind == "mission_item_reached":
        mav.mission_item_reached_send(1)
    elif kind == "sys_status":
        mav.sys_status_send(0, 0, 0, 0, 16000, 100, 90, 0, 0, 0, 0, 0, 0)
    else:
        mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@settings(max_examples=ORDERS, deadline=None)
@given(st.permutations(KINDS + KINDS))
def test_any_order_of_valid_messages_is_read_without_a_crash(tmp_path_factory, order):
    tmp = tmp_path_factory.mktemp("order")
    port = free_port()
    text = agent_toml("uav1", "worker", 1, f"udpin:127.0.0.1:{port}", tmp / "runs", free_port(), [])
    path = tmp / "agent.toml"
    path.write_text(text)
    agent = Agent(parse_agent_config(read_toml(path, "agent config"), str(path)), tmp / "runs" / "test" / "uav1")
    autopilot = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        agent.open()
        for kind in order:
            send(autopilot.mav, kind)
            select.select(agent.autopilot.readers(), [], [], 0.2)
            agent._read_autopilot(time.monotonic())
            agent.autopilot.check(time.monotonic())
        assert agent.autopilot.up, "the heartbeat, whenever it came, brought the link up"
    finally:
        autopilot.close()
        agent.close()
    print(f"order {len(order)} messages read: {' '.join(k[:4] for k in order)}")
