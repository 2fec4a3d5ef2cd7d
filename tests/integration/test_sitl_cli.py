"""`nac-sitl run` as users start it: a subprocess that prints its endpoints and stops on Ctrl-C."""

import subprocess
import sys

from missions.model import MavCmd
from sitl.launcher import SitlProcess
from sitl.server import SitlConfig
from tests.integration.gcs import Gcs


def test_cli_serves_vehicles_over_udp_and_tcp_and_stops_on_sigint(base_port, tmp_path):
    base = base_port(2)
    params = tmp_path / "copter.parm"
    params.write_text("# NAC gains\nNAC_KP_XY 0.2\nWPNAV_SPEED,300\n")
    config = SitlConfig(vehicles=2, speedup=5.0, gcs_base_port=base, companion_base_port=base + 1,
                        tcp_base_port=base_port(2))
    proc = SitlProcess(config, ["--params", str(params)]).start()
    try:
        assert any(f"ground udp 127.0.0.1:{base + 10}" in line for line in proc.banner)
        gcs = Gcs(base + 10, sysid=2)
        hb = gcs.wait_heartbeat()
        assert hb.autopilot == 3 and hb.type == 2
        gcs.conn.mav.param_request_read_send(2, 1, b"NAC_KP_XY", -1)
        assert abs(gcs.recv("PARAM_VALUE", 3.0).param_value - 0.2) < 1e-6
        assert gcs.command(MavCmd.COMPONENT_ARM_DISARM, 1) == 0
        gcs.close()

        from pymavlink import mavutil
        tcp = mavutil.mavlink_connection(f"tcp:127.0.0.1:{config.tcp_base_port}", source_system=254)
        try:
            assert tcp.wait_heartbeat(timeout=5) is not None and tcp.target_system == 1
        finally:
            tcp.close()
    finally:
        code = proc.stop()
    assert code == 0


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "sitl.cli", *args], capture_output=True, text=True, timeout=30)


def test_bad_parameter_file_is_exit_2_naming_file_and_line(tmp_path):
    bad = tmp_path / "bad.parm"
    bad.write_text("NAC_KP_XY 0.2\nWPNAV_SPEED fast\n")
    result = run_cli("run", "--params", str(bad))
    assert result.returncode == 2
    assert f"{bad}:2" in result.stderr and "not a number" in result.stderr
    assert "Traceback" not in result.stderr
    unknown = tmp_path / "unknown.parm"
    unknown.write_text("NOPE 1\n")
    result = run_cli("run", "--params", str(unknown))
    assert result.returncode == 2 and "unknown parameter 'NOPE'" in result.stderr


def test_bad_arguments_are_exit_2(tmp_path):
    result = run_cli("run", "--home", "1,2")
    assert result.returncode == 2 and "LAT,LON,ALT_M" in result.stderr
    result = run_cli("run", "--vehicles", "0")
    assert result.returncode == 2 and "--vehicles" in result.stderr
    result = run_cli("run", "--params", str(tmp_path / "missing.parm"))
    assert result.returncode == 2 and "missing.parm" in result.stderr
    empty_key = tmp_path / "empty.key"
    empty_key.write_text("\n")
    result = run_cli("run", "--signing-key-file", str(empty_key))
    assert result.returncode == 2 and "empty.key is empty" in result.stderr


def test_taken_tcp_port_is_a_clear_error(base_port):
    import socket

    base = base_port(1)
    with socket.socket() as holder:
        holder.bind(("0.0.0.0", base + 100))
        holder.listen()
        result = run_cli("run", "--gcs-base-port", str(base), "--companion-base-port", str(base + 1),
                         "--tcp-base-port", str(base + 100))
    assert result.returncode == 1 and f"TCP port {base + 100}" in result.stderr
