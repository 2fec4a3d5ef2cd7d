"""Our throughput probe and real iperf3 measure the same paths: loopback, and a 10 Mbit/s `tc tbf` link between
two network namespaces."""

import dataclasses
import json
import os
import secrets
import socket
import statistics
import subprocess
import sys
import threading
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nac_onboard.agent.config import ThroughputSection
from nac_onboard.agent.peers import HeardPeer, PeerState
from nac_onboard.agent.probes import ProbeScheduler
from nac_onboard.agent.snapshot import AgentSnapshot, OwnState
from nac_onboard.flight_log import JsonlLog, read_jsonl
from nac_onboard.link import iperf3
from nac_onboard.link.emulation import SleepEmulation
from nac_onboard.link.iperf3 import compare, iperf3_result, iperf3_server, nac_server
from nac_onboard.link.throughput import ThroughputServer
from nac_onboard.radio.channel import PRESETS
from tests.conftest import free_port

needs_iperf3 = pytest.mark.skipif(not iperf3.available(), reason="iperf3 not installed (.ci/run installs it)")


@needs_iperf3
def test_records_read_like_iperf3_json():
    port, iperf_port = free_port(), free_port()
    with nac_server(port), iperf3_server(iperf_port):
        ours = json.loads(subprocess.run([sys.executable, "-m", "nac_onboard.cli", "throughput", "probe",
                                          "127.0.0.1", "--port", str(port), "-t", "1", "-i", "0.2"],
                                         capture_output=True, text=True, timeout=30, check=True).stdout)
        theirs = iperf3_result("127.0.0.1", iperf_port, duration_s=1)
    assert set(theirs["intervals"][0]["sum"]) <= set(ours["intervals"][0]["sum"])
    assert set(theirs["intervals"][0]["streams"][0]) - {"socket"} <= set(ours["intervals"][0]["streams"][0])
    for key in ("sum_sent", "sum_received"):
        assert set(theirs["end"][key]) <= set(ours["end"][key])
    assert 4 <= len(ours["intervals"]) <= 6, "1 s in 0.2 s intervals"
    total = sum(i["sum"]["bytes"] for i in ours["intervals"])
    assert total == ours["end"]["sum_sent"]["bytes"] >= ours["end"]["sum_received"]["bytes"] > 0


@pytest.fixture
def netns():
    """Factory: run setup commands to build network namespaces (root only); all are deleted at the end."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces and tc need root")
    made: list[str] = []

    def build(names: list[str], steps: list[list[str]]) -> None:
        try:
            for name in names:
                subprocess.run(["ip", "netns", "add", name], check=True, capture_output=True, timeout=30)
                made.append(name)
            for step in steps:
                subprocess.run(step, check=True, capture_output=True, timeout=30)
        except subprocess.CalledProcessError as err:
            pytest.fail(f"could not build the test network ({' '.join(err.cmd)}): {err.stderr.decode().strip()}")

    yield build
    for name in made:
        subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=30)


@needs_iperf3
@pytest.mark.exclusive  # rates or times measured against a bound
def test_loopback_rate_agrees_with_iperf3_within_10_percent(netns):
    # Plain loopback measures the CPU, not a path: both tools are CPU-bound there and a shared 2-core machine
    # swings their rates by +-30 % from run to run (benchmarks/throughput_vs_iperf3.py records that comparison).
    # So the loopback of a private namespace, capped by tbf well below what a slow CI core moves (it fell short of
    # a 2 Gbit/s cap there), is the path both must agree on.
    ns = f"nac-{secrets.token_hex(3)}-lo"
    netns([ns], [["ip", "-n", ns, "link", "set", "lo", "up"],
                 ["ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", "lo", "root", "tbf", "rate", "400mbit",
                  "burst", "256kb", "latency", "20ms"]])
    result = compare("127.0.0.1", runs=3, duration_s=1, netns_client=ns, netns_server=ns)
    assert 360e6 < statistics.median(result.iperf3_bps) < 420e6, f"iperf3 sees the 400 Mbit/s cap: {result.iperf3_bps}"
    assert abs(result.ratio - 1) < 0.10, result.describe(1e6, "Mbit/s")


@needs_iperf3
@pytest.mark.exclusive  # rates or times measured against a bound
def test_rate_limited_link_agrees_with_iperf3_within_10_percent(netns):
    """Two namespaces joined by a veth pair; the client side leaves through an htb class of 10 Mbit/s. iperf3's
    median run is the sanity check, as the ratio is a median of pairs: one 1-second run can lose half its second to
    the kernel's deferred teardown of namespaces an earlier test removed (CI saw 9.1, 9.5 and 5.3 Mbit/s).
    Not tbf: with the 4 KB bucket this test once used, tbf dropped 2.6 packets for every one it sent (veth hands it
    segments larger than the bucket), and one 1-second run in five, of either tool, stalled to 6.4-8.2 Mbit/s in
    recovery; CI once caught ours in two of three. htb drops none here: 32 runs of each tool gave 9.53-9.66."""
    tag = secrets.token_hex(3)
    a, b, va, vb = f"nac-{tag}-a", f"nac-{tag}-b", f"nv{tag}a", f"nv{tag}b"
    netns([a, b], [["ip", "link", "add", va, "netns", a, "type", "veth", "peer", "name", vb, "netns", b],
                   ["ip", "-n", a, "addr", "add", "10.77.0.1/24", "dev", va],
                   ["ip", "-n", b, "addr", "add", "10.77.0.2/24", "dev", vb],
                   ["ip", "-n", a, "link", "set", va, "up"], ["ip", "-n", b, "link", "set", vb, "up"],
                   ["ip", "netns", "exec", a, "tc", "qdisc", "add", "dev", va, "root", "handle", "1:", "htb",
                    "default", "1"],
                   ["ip", "netns", "exec", a, "tc", "class", "add", "dev", va, "parent", "1:", "classid", "1:1",
                    "htb", "rate", "10mbit"]])
    result = compare("10.77.0.2", runs=3, duration_s=1, netns_client=a, netns_server=b)
    assert 8e6 < statistics.median(result.iperf3_bps) < 10.5e6, f"iperf3 sees 10 Mbit/s: {result.iperf3_bps}"
    assert abs(result.ratio - 1) < 0.10, result.describe(1e6, "Mbit/s")


@pytest.mark.exclusive  # rates or times measured against a bound
def test_emulated_probes_follow_the_channel_model_at_the_live_distance(tmp_path):
    """SITL's probes: paced at the model's capacity for the pair's distance, failing beyond its range, skipped
    (not failed) while a position is unknown."""
    server = ThroughputServer("127.0.0.1", free_port()).start()
    east_m = {"value": 10.0}

    def positions():
        peers = () if east_m["value"] is None else (
            HeardPeer(PeerState("w", "worker", 0.0, lat_deg=47.0, lon_deg=8.0 + east_m["value"] / 75_840.0,
                                alt_m=500.0), 0.1, False),)
        return AgentSnapshot(0.0, _own_state(), peers)

    settings = ThroughputSection(probe=True, duration_s=0.5, interval_s=0.1, emulate_channel="wifi-flight")
    wifi = dataclasses.replace(PRESETS["wifi-flight"], shadowing_sigma_db=0.0, rician_k_db=None)  # the median link
    emulation = SleepEmulation(wifi)
    try:
        with JsonlLog(tmp_path / "throughput.jsonl") as out:
            scheduler = ProbeScheduler(settings, "m", lambda: [], positions, out, threading.Event(), emulation)
            near = scheduler.probe_once("w", "127.0.0.1", server.port)
            (latest,) = scheduler.results()  # what the state feed hands the MPI master (--link-rates probes)
            east_m["value"] = 30.0
            far = scheduler.probe_once("w", "127.0.0.1", server.port)
            east_m["value"] = None
            unknown = scheduler.probe_once("w", "127.0.0.1", server.port)
    finally:
        server.stop()
    capacity = wifi.capacity_bps(near["distance_m"])
    assert 9.9 < near["distance_m"] < 10.1 and near["emulated_rate_bps"] == capacity
    measured = near["end"]["sum_received"]["bits_per_second"]
    assert abs(measured - capacity) / capacity < 0.05, (measured, capacity)
    assert latest.peer == "w" and latest.bits_per_second == measured and 0 <= latest.age_s < 5
    assert far["error"].startswith("out of range: wifi-flight gives") and far["distance_m"] > 29
    assert scheduler.results()[0].bits_per_second == 0.0, "a failed probe: nothing gets through"
    assert unknown["kind"] == "probe_skipped"
    kinds = [r["kind"] for r in read_jsonl(tmp_path / "throughput.jsonl").records]
    assert kinds == ["throughput", "throughput", "probe_skipped"]


def _own_state() -> OwnState:
    return OwnState("m", "master", 1, 47.0, 8.0, 500.0, None, None, "", True)


@needs_iperf3
def test_probes_can_run_the_real_iperf3_and_log_its_json(tmp_path):
    """throughput.tool = "iperf3": the agent's probe schedule runs `iperf3 --client --json` (whole seconds) and
    logs iperf3's own result; a target without a server is a failed probe, logged, not a crash."""
    port, closed = free_port(), free_port()
    settings = ThroughputSection(probe=True, duration_s=0.5, interval_s=0.1, tool="iperf3")
    positions = AgentSnapshot(0.0, _own_state())
    with iperf3_server(port), JsonlLog(tmp_path / "throughput.jsonl") as out:
        scheduler = ProbeScheduler(settings, "m", lambda: [], lambda: positions, out, threading.Event())
        measured = scheduler.probe_once("w", "127.0.0.1", port)
        failed = scheduler.probe_once("w", "127.0.0.1", closed)
    assert measured["duration_wall_s"] == 1 and measured["start"]["test_start"]["duration"] == 1
    assert measured["end"]["sum_received"]["bits_per_second"] > 1e6, "iperf3's own fields, as it wrote them"
    assert failed["error_kind"] == "link" and str(closed) in failed["error"]
    assert [r["kind"] for r in read_jsonl(tmp_path / "throughput.jsonl").records] == ["throughput", "throughput"]


@pytest.mark.parametrize("tool", ["nac", pytest.param("iperf3", marks=needs_iperf3)])
def test_a_stop_ends_a_probe_under_way_at_once_and_logs_it_skipped(tmp_path, tool):
    """A probe to a host that takes the connection and then says nothing (a listening socket nobody accepts from)
    would wait for its own deadlines: 10 s of sending, then the server's grace and the answer's margin (ours), or
    its 20 s timeout (iperf3's client). The agent's stop ends it within the 5 s its runner gives an agent to stop
    (here it takes milliseconds: a shutdown or a kill, then a thread's end, so a loaded host cannot stretch it to
    seconds), and it is logged as skipped (it measured nothing), not as a failed link."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(4)
    stop = threading.Event()
    settings = ThroughputSection(probe=True, duration_s=10.0, interval_s=1.0, tool=tool)
    try:
        with JsonlLog(tmp_path / "throughput.jsonl") as out:
            scheduler = ProbeScheduler(settings, "m", lambda: [], lambda: AgentSnapshot(0.0, _own_state()), out, stop)
            probing = threading.Thread(target=scheduler.probe_once, args=("w", "127.0.0.1",
                                                                          listener.getsockname()[1]))
            probing.start()
            deadline = time.monotonic() + 10.0
            while not scheduler._under_way and time.monotonic() < deadline:
                time.sleep(0.01)  # until the probe has connected (iperf3 is a process to start)
            assert scheduler._under_way, "the probe connected"
            stopped_at = time.monotonic()
            stop.set()
            scheduler.abort()
            probing.join(10.0)
            took_s = time.monotonic() - stopped_at
    finally:
        listener.close()
    assert not probing.is_alive() and took_s < 5.0, took_s
    (record,) = read_jsonl(tmp_path / "throughput.jsonl").records
    assert record["kind"] == "probe_skipped" and record["reason"] == "the agent stopped during the probe"


HEADER_FUZZ_EXAMPLES = 300
BAD_HEADERS = [b"[1, 2]\n", b"42\n", b"null\n", b"[" * 4000 + b"\n", b'{"protocol": "nac-probe/1"}\n',
               b'{"protocol": "nac-probe/1", "duration_s": 1, "interval_s": [1]}\n',
               b'{"protocol": "nac-probe/1", "duration_s": 1, "interval_s": ' + b"9" * 400 + b"}\n",
               b'{"protocol": "nac-probe/1", "duration_s": 1, "interval_s": -1}\n',
               b'{"protocol": "nac-probe/1", "duration_s": NaN}\n', b'{"protocol": "nac-probe/1", "bytes": -5}\n',
               b'{"protocol": "nac-probe/1", "duration_s": 1e9}\n', b'{"protocol": "iperf"}\n', b"\xff\xfe\n"]


@pytest.mark.exclusive  # rates or times measured against a bound
def test_the_server_refuses_malformed_headers_and_silent_clients_and_keeps_serving():
    """7 of 12 malformed headers once killed the server, a silent client blocked it, and interval_s -1 with
    1-byte writes grew it to 1 GB: each is refused with an answer, and a real probe still runs after them."""
    import socket

    from nac_onboard.link.throughput import HEADER_TIMEOUT_S, ProbeError, probe

    server = ThroughputServer("127.0.0.1", free_port()).start()
    try:
        for header in BAD_HEADERS:
            with socket.create_connection(("127.0.0.1", server.port), timeout=5.0) as conn:
                conn.sendall(header)
                conn.shutdown(socket.SHUT_WR)
                answer = json.loads(conn.makefile("rb").readline())
            assert "error" in answer, header
        silent = socket.create_connection(("127.0.0.1", server.port), timeout=5.0)
        try:
            t0 = time.monotonic()
            answer = json.loads(silent.makefile("rb").readline())  # the server gives up on it, not the reverse
            assert "no probe header" in answer["error"] and time.monotonic() - t0 < HEADER_TIMEOUT_S + 1.0
        finally:
            silent.close()
        assert server.alive and server.refused == len(BAD_HEADERS) + 1
        result = probe("127.0.0.1", server.port, duration_s=0.3, interval_s=0.1)
        assert result["end"]["sum_received"]["bytes"] > 0
    finally:
        server.stop()
    with pytest.raises(ProbeError) as err:  # nobody there: the link's fault, not a server's
        probe("127.0.0.1", free_port(), duration_s=0.2, connect_timeout_s=1.0)
    assert err.value.kind == "link"


@settings(max_examples=HEADER_FUZZ_EXAMPLES, deadline=None)
@given(st.binary(max_size=600) | st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.sampled_from(
        ["protocol", "duration_s", "bytes", "interval_s", "x"]), inner, max_size=5), max_leaves=12)
       .map(lambda v: json.dumps(v).encode()))
def test_fuzzed_probe_headers_are_checked_or_refused_never_raised_otherwise(line):
    from nac_onboard.link.throughput import HeaderError, check_header

    try:
        header = check_header(line)
    except HeaderError:
        return
    assert (header["duration_s"] is None) != (header["bytes"] is None) and header["interval_s"] >= 0.05
