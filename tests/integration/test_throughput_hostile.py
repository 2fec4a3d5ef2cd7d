"""The throughput probe and server on a hostile network (issue 34): a server's answer is checked field by field and
a wrong one is a `server` failure (never a crash, a traceback or `Infinity` in JSON); idle, trickling and endless
connections cannot keep a genuine probe out or hold the server; a path that stops carrying data mid-probe is a
`link` failure, kept in the analysis; the master's probe schedule survives any one probe."""

import json
import os
import secrets
import select
import socket
import subprocess
import sys
import threading
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ground.logs.analysis import throughput as analysis_throughput
from ground.logs.run_clock import RunClock
from ground.logs.runlog import RunLog
from nac_onboard.agent.config import ThroughputSection
from nac_onboard.agent.probes import ProbeScheduler
from nac_onboard.agent.snapshot import AgentSnapshot, OwnState
from nac_onboard.clock import Clock
from nac_onboard.flight_log import JsonlLog, read_jsonl
from nac_onboard.link import throughput
from nac_onboard.link.throughput import (
    ANSWER_MARGIN_S,
    GRACE_S,
    HEADER_TIMEOUT_S,
    MAX_INTERVALS,
    MAX_PENDING,
    MAX_PROBE_S,
    MAX_PROBES,
    PROTOCOL,
    ProbeError,
    ThroughputServer,
    check_answer,
    probe,
)
from tests.conftest import REPO, free_port

SENT_BYTES = 2000  # what the probes below send (-n): an answer may count at most this many
# the latest end an answer may claim, as probe() allows it for a probe by bytes (a test that assumed 60 s drew
# end = 61 s, which the probe rightly took: a probe by bytes may run its 60 s, the grace and the answer's margin)
MAX_END_S = MAX_PROBE_S + GRACE_S + ANSWER_MARGIN_S


class HostileServer:
    """A real TCP server playing a broken throughput server: it reads each probe to its end and answers `answer`
    (bytes, as they are), or with stall=True reads the header and a little data, then neither reads nor answers
    (a path that stopped carrying data) until closed."""

    def __init__(self, answer: bytes = b"", stall: bool = False):
        self.answer, self.stall = answer, stall
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.stalled = threading.Event()  # set once a stalled probe holds its connection
        self._held: list[socket.socket] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        self.sock.settimeout(0.2)
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.settimeout(5.0)
            try:
                if self.stall:
                    conn.recv(65536)  # the header and whatever came with it; then nothing more is read
                    self._held.append(conn)
                    self.stalled.set()
                    continue
                while conn.recv(65536):
                    pass
                conn.sendall(self.answer)
            except OSError:
                pass
            conn.close()

    def close(self) -> None:
        self._stop.set()
        self.sock.close()
        self._thread.join(timeout=5.0)
        for conn in self._held:
            conn.close()


@pytest.fixture
def hostile():
    servers: list[HostileServer] = []

    def make(answer: bytes = b"", stall: bool = False) -> HostileServer:
        servers.append(HostileServer(answer, stall))
        return servers[-1]

    yield make
    for server in servers:
        server.close()


# ---- bad answers ---------------------------------------------------------------------------------------------

_GOOD = {"start": 0, "end": 0.3, "bytes": SENT_BYTES // 2}
_NOT_A_NUMBER = (st.none() | st.booleans() | st.text(max_size=8) | st.lists(st.integers(), max_size=2)
                 | st.dictionaries(st.text(max_size=3), st.integers(), max_size=2)
                 | st.sampled_from([float("nan"), float("inf"), float("-inf")]))
_BAD_TIME = _NOT_A_NUMBER | st.floats(max_value=-1e-9) | st.floats(min_value=MAX_END_S * 1.001) | st.integers(
    max_value=-1)
_BAD_BYTES = (_NOT_A_NUMBER | st.integers(max_value=-1) | st.integers(min_value=SENT_BYTES + 1)
              | st.floats(allow_nan=True, allow_infinity=True))


@st.composite
def bad_sum(draw) -> object:
    """A sum_received (or an interval's sum) that is not a measurement: not an object, a field missing, or a
    field of the wrong type, not finite, negative, beyond the probe or what was sent, or ending before it starts."""
    shape = draw(st.sampled_from(["not-object", "missing", "start", "end", "bytes", "backwards"]))
    if shape == "not-object":
        return draw(st.none() | st.text(max_size=5) | st.integers() | st.lists(st.integers(), max_size=3))
    value = dict(_GOOD)
    if shape == "missing":
        del value[draw(st.sampled_from(sorted(value)))]
    elif shape == "backwards":
        value.update(start=draw(st.floats(0.5, MAX_END_S)), end=draw(st.floats(0.0, 0.49)))
    else:
        value[shape] = draw(_BAD_BYTES if shape == "bytes" else _BAD_TIME)
    return value


@st.composite
def bad_answer(draw) -> bytes:
    """A whole answer line the probe must refuse as the server's fault."""
    shape = draw(st.sampled_from(["sum_received", "interval", "intervals", "overcount", "top", "error", "raw"]))
    if shape == "sum_received":
        answer = {"sum_received": draw(bad_sum()), "intervals": []}
    elif shape == "interval":
        answer = {"sum_received": _GOOD, "intervals": [{"sum": _GOOD}, {"sum": draw(bad_sum())}]}
    elif shape == "intervals":
        answer = {"sum_received": _GOOD, "intervals": draw(
            st.none() | st.integers() | st.text(max_size=4) | st.lists(st.none() | st.integers(), min_size=1,
                                                                        max_size=3)
            | st.just([{"sum": _GOOD}] * (MAX_INTERVALS + 1)))}
    elif shape == "overcount":  # intervals that add up to more than the total
        answer = {"sum_received": _GOOD, "intervals": [{"sum": _GOOD}] * draw(st.integers(2, 5))}
    elif shape == "top":
        answer = draw(st.none() | st.integers() | st.text(max_size=5) | st.lists(st.integers(), max_size=3)
                      | st.just({}) | st.just({"intervals": []}))
    elif shape == "error":
        answer = {"error": draw(st.text(max_size=40) | st.integers() | st.none() | st.lists(st.integers())),
                  "error_kind": draw(st.sampled_from(["server", "", 5, None, "LINK"]))}
    else:
        return draw(st.binary(max_size=200).filter(lambda b: not _is_json(b))) + b"\n"
    return json.dumps(answer).encode() + b"\n"  # NaN and Infinity as Python writes them


def _is_json(raw: bytes) -> bool:
    try:
        json.loads(raw)
    except (ValueError, RecursionError):
        return False
    return True


@settings(max_examples=400, deadline=None)
@given(bad_answer())
def test_bad_answers_of_every_shape_are_refused_as_the_servers_fault(raw):
    with pytest.raises(ProbeError) as err:
        check_answer(raw, "10.0.0.2:5201", SENT_BYTES, MAX_END_S)
    assert err.value.kind == "server" and "10.0.0.2:5201" in str(err.value)
    assert "\n" not in str(err.value), "a server's text is shown as one printable line"


@settings(max_examples=300, deadline=None)
@given(st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=6),
                    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.sampled_from(
                        ["sum_received", "intervals", "sum", "start", "end", "bytes", "error", "x"]), inner,
                        max_size=4), max_leaves=15))
def test_any_answer_is_refused_or_gives_finite_non_negative_figures(answer):
    try:
        received, intervals = check_answer(json.dumps(answer).encode() + b"\n", "h:1", SENT_BYTES, MAX_END_S)
    except ProbeError as err:
        assert err.kind == "server"
        return
    json.dumps([received, intervals], allow_nan=False)  # never NaN or Infinity
    for s in [received] + [i["sum"] for i in intervals]:
        assert 0 <= s["start"] <= s["end"] <= MAX_END_S and 0 <= s["bytes"] <= SENT_BYTES
        assert s["bits_per_second"] >= 0


def test_a_checked_answer_is_a_measurement():
    """The positive control of the two above: a well-formed answer is taken, its rate computed from its fields."""
    received, intervals = check_answer(json.dumps({"sum_received": _GOOD, "intervals": [{"sum": _GOOD}]}).encode(),
                                       "h:1", SENT_BYTES, MAX_END_S)
    assert received["bytes"] == SENT_BYTES // 2 and received["bits_per_second"] == pytest.approx(8000 / 0.3)
    assert intervals[0]["sum"] == received


@pytest.fixture(scope="module")
def answering():
    server = HostileServer()
    yield server
    server.close()


@settings(max_examples=60, deadline=None)
@given(raw=bad_answer())
def test_a_probe_to_a_server_answering_wrongly_fails_as_a_server_failure(answering, raw):
    """End to end over TCP: the probe runs, the answer comes back wrong, the probe raises ProbeError("server")."""
    answering.answer = raw
    with pytest.raises(ProbeError) as err:
        probe("127.0.0.1", answering.port, duration_s=None, nbytes=SENT_BYTES, interval_s=0.05)
    assert err.value.kind == "server", str(err.value)


CLI_BAD_ANSWERS = [b'{"sum_received": ""}\n', b'{"sum_received": {}}\n', b'{"sum_received": []}\n',
                   b'{"sum_received": {"start": 0, "end": Infinity, "bytes": 5}}\n',
                   b'{"sum_received": {"start": 0, "end": 1, "bytes": -5}}\n',
                   b'{"sum_received": {"start": 0, "end": 1e-300, "bytes": 5}, "intervals": "x"}\n',
                   b'{"error": 5}\n', b"\x1b[2J not json\n", b""]


def test_the_probe_cli_says_one_sentence_and_exits_1_on_every_bad_answer(hostile):
    server = hostile()
    for raw in CLI_BAD_ANSWERS:
        server.answer = raw
        done = subprocess.run([sys.executable, "-m", "nac_onboard.cli", "throughput", "probe", "127.0.0.1",
                               "--port", str(server.port), "-n", str(SENT_BYTES), "-i", "0.05"],
                              capture_output=True, text=True, timeout=60, cwd=REPO)
        assert done.returncode == 1, (raw, done.stdout, done.stderr)
        assert done.stdout == "" and "Traceback" not in done.stderr, (raw, done.stderr)
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"nac-onboard: throughput server 127.0.0.1:{server.port}")
        assert "\x1b" not in done.stderr, "the server's bytes never reach the terminal raw"
    for bad in (["--port", "70000"], ["-t", "nan"], ["-t", "-1"], ["-n", "0"], ["-i", "0"], ["-b", "inf"]):
        done = subprocess.run([sys.executable, "-m", "nac_onboard.cli", "throughput", "probe", "127.0.0.1", *bad],
                              capture_output=True, text=True, timeout=60, cwd=REPO)
        assert done.returncode == 2 and "Traceback" not in done.stderr and done.stderr.strip(), (bad, done.stderr)
    done = subprocess.run([sys.executable, "-m", "nac_onboard.cli", "throughput", "server", "--port", "70000"],
                          capture_output=True, text=True, timeout=60, cwd=REPO)
    assert done.returncode == 2 and "Traceback" not in done.stderr and "--port" in done.stderr, done.stderr


# ---- a path that stops carrying data -------------------------------------------------------------------------

def test_a_server_that_stops_reading_and_answering_mid_probe_is_a_link_failure(hostile):
    """The server takes the header and some data, then nothing: the probe waits out its deadline (its length +
    GRACE_S + ANSWER_MARGIN_S), not forever, and says the link failed."""
    server = hostile(stall=True)
    t0 = time.monotonic()
    with pytest.raises(ProbeError) as err:
        probe("127.0.0.1", server.port, duration_s=0.3, interval_s=0.1)
    assert server.stalled.is_set()
    assert err.value.kind == "link" and "stalled" in str(err.value)
    assert time.monotonic() - t0 < 0.3 + GRACE_S + ANSWER_MARGIN_S + 5.0, "every wait of the probe has a deadline"


BLACKHOLE_SCRIPT = r"""
import json, subprocess, sys, threading, time
from nac_onboard.link.throughput import ProbeError, ThroughputServer, probe
port, ns = int(sys.argv[1]), sys.argv[2]
server = ThroughputServer("127.0.0.1", port).start()
def blackhole():
    # once the probe is being received, drop everything toward the server's port: one way only, the answers
    # from it still get through
    deadline = time.monotonic() + 10
    while not server._probes and time.monotonic() < deadline:
        time.sleep(0.01)
    done = subprocess.run(["nft", "-f", "-"], input=(
        "table inet nacbh {\n chain toserver {\n  type filter hook input priority 0;\n  tcp dport %d drop\n }\n}\n"
        % port),
        text=True, capture_output=True)
    holed.append(done.returncode == 0 and bool(server._probes) or done.stderr or "no probe started")
holed = []
threading.Thread(target=blackhole, daemon=True).start()
t0 = time.monotonic()
try:
    probe("127.0.0.1", port, duration_s=1.5, interval_s=0.1, rate_bps=50e6)
    out = {"kind": None}
except ProbeError as err:
    out = {"kind": err.kind, "error": str(err)}
out["elapsed_s"], out["blackhole"] = time.monotonic() - t0, holed
print(json.dumps(out))
"""


def test_a_one_way_blackhole_mid_probe_is_a_link_failure_kept_in_the_analysis():
    """The issue's case: data toward the server dropped mid-probe (nft in a private namespace), its answers still
    coming back. The server cuts the probe at its length + GRACE_S, sees the data had stopped and says so; the
    probe is a link failure, and the analysis keeps it as a zero."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces and nft need root")
    ns = f"nac-{secrets.token_hex(3)}-bh"
    subprocess.run(["ip", "netns", "add", ns], check=True, capture_output=True, timeout=30)
    try:
        subprocess.run(["ip", "-n", ns, "link", "set", "lo", "up"], check=True, capture_output=True, timeout=30)
        done = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-c", BLACKHOLE_SCRIPT,
                               str(free_port()), ns], capture_output=True, text=True, timeout=60, cwd=REPO)
    finally:
        subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["blackhole"] == [True], out
    assert out["kind"] == "link" and "stalled" in out["error"], out
    record = {"kind": "throughput", "t_s": 100.0, "client": "m", "server": "w", "error": out["error"],
              "error_kind": out["kind"], "distance_m": 20.0}
    table = analysis_throughput(RunLog(REPO, probes=[record]), RunClock.of(0.0))
    assert len(table) == 1 and table["throughput_mbps"].iloc[0] == 0.0, "a dead link is a measurement: zero"


# ---- idle, trickling and endless connections -----------------------------------------------------------------

def _connect_from(source: str, port: int) -> socket.socket:
    conn = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    conn.bind((source, 0))
    conn.settimeout(5.0)
    conn.connect(("127.0.0.1", port))
    return conn


@pytest.mark.exclusive  # rates or times measured against a bound
def test_a_genuine_probe_measures_the_link_while_500_idle_and_trickling_connections_are_open():
    """500 hostile connections from five addresses (idle; trickling their header; a valid header, then a byte now
    and then), plus 20 idle ones from the prober's own address, are open when the probe starts: it still connects
    and measures its 20 Mbit/s cap within 10 %. The bound holds on a loaded 2-core machine: the sender is paced
    at 2.5 MB/s, a small fraction of what loopback moves on one busy core, and the receiver is a thread of its
    own; the tricklers' one byte per 0.2 s and the server's accept loop cost next to nothing (before the fix
    every such probe failed: the server served one connection at a time and the backlog filled)."""
    server = ThroughputServer("127.0.0.1", free_port()).start()
    hostile: list[socket.socket] = []
    trickling: list[socket.socket] = []
    header = json.dumps({"protocol": PROTOCOL, "duration_s": 30, "interval_s": 1}).encode() + b"\n"
    stop = threading.Event()

    def trickle() -> None:
        while not stop.wait(0.2):
            for conn in trickling:
                try:
                    conn.send(b"x")
                except OSError:
                    pass

    trickler = threading.Thread(target=trickle, daemon=True)
    try:
        for n in range(500):
            conn = _connect_from(f"127.0.0.{2 + n % 5}", server.port)
            hostile.append(conn)
            if n % 3 == 1:
                conn.send(header[:10])  # a header that never ends
            elif n % 3 == 2:
                conn.send(header)  # a valid probe that hardly sends
                trickling.append(conn)
        hostile += [_connect_from("127.0.0.1", server.port) for _ in range(20)]
        trickler.start()
        result = probe("127.0.0.1", server.port, duration_s=1.0, interval_s=0.25, rate_bps=20e6)
        measured_bps = result["end"]["sum_received"]["bits_per_second"]
        assert abs(measured_bps - 20e6) / 20e6 < 0.10, measured_bps
        assert server.alive and server.shed > 0, "connections over the caps were closed"
        assert server.open_connections <= MAX_PENDING + MAX_PROBES
    finally:
        stop.set()
        server.stop()
        for conn in hostile:
            conn.close()
        if trickler.is_alive():
            trickler.join(timeout=5.0)


@pytest.mark.exclusive  # rates or times measured against a bound
@pytest.mark.parametrize("speedup", [1.0, 4.0])
def test_a_client_sending_forever_is_cut_at_the_probes_length_plus_the_grace(speedup):
    """A client declares a 0.5 s probe and never stops sending: the server cuts it at 0.5 s + GRACE_S (the
    documented bound; it once took 120 s), not before; GRACE_S is the run's time, a quarter as long on the wall
    clock at 4x. The bound holds on a loaded machine: the cut is the server's accept thread noticing a deadline it
    checks every 0.25 s, with 1.5 s of slack."""
    grace_s = GRACE_S / speedup
    server = ThroughputServer("127.0.0.1", free_port(), sped_up(speedup)).start()
    try:
        with socket.create_connection(("127.0.0.1", server.port), timeout=5.0) as conn:
            conn.sendall(json.dumps({"protocol": PROTOCOL, "duration_s": 0.5, "interval_s": 0.1}).encode() + b"\n")
            t0 = time.monotonic()
            conn.setblocking(False)
            block, cut = b"\0" * 65536, False
            while not cut and time.monotonic() - t0 < 0.5 + grace_s + 10:
                readable, writable, _ = select.select([conn], [conn], [], 0.1)
                try:
                    if readable:
                        conn.recv(65536)  # the server's answer, or b"" as it closes: either way, cut
                        cut = True
                    elif writable:
                        conn.send(block)
                except BlockingIOError:
                    pass
                except OSError:  # reset: cut too
                    cut = True
            elapsed_s = time.monotonic() - t0
        assert cut and 0.5 + grace_s - 0.5 <= elapsed_s <= 0.5 + grace_s + 1.5, elapsed_s
        assert server.alive and server.refused == 1
        result = probe("127.0.0.1", server.port, duration_s=0.2, interval_s=0.1)  # and it serves the next one
        assert result["end"]["sum_received"]["bytes"] > 0
    finally:
        server.stop()


@pytest.mark.parametrize("speedup", [1.0, 0.25])
def test_a_pause_in_a_probes_data_is_a_stall_only_past_the_idle_limit_in_the_runs_seconds(monkeypatch, speedup):
    """The server calls a probe stalled when no data came for IDLE_TIMEOUT_S, the run's seconds below 1x: at 0.1x
    ten wall seconds were one simulated second, less than a slowed air's full queue holds, and probes that were
    only queued failed as stalled. With the limit at 0.5 s, a 1 s pause stalls the probe at 1x and not at 0.25x
    (2 wall seconds); a loaded machine's late wake-up cannot shorten the pause, and it would take another second to
    reach 0.25x's limit."""
    monkeypatch.setattr(throughput, "IDLE_TIMEOUT_S", 0.5)
    server, answer = ThroughputServer("127.0.0.1", free_port(), sped_up(speedup)).start(), None
    try:
        with socket.create_connection(("127.0.0.1", server.port), timeout=10.0) as conn:
            try:
                conn.sendall(json.dumps({"protocol": PROTOCOL, "duration_s": 2.0, "interval_s": 0.5}).encode()
                             + b"\n" + b"\0" * 65536)
                time.sleep(1.0)
                conn.sendall(b"\0" * 65536)
                conn.shutdown(socket.SHUT_WR)
                answer = json.loads(conn.makefile().readline() or "null")
            except OSError:
                pass  # the server broke the probe off and closed it: counted in server.refused
    finally:
        server.stop()
    if speedup < 1.0:
        assert server.refused == 0 and answer["sum_received"]["bytes"] == 2 * 65536, answer
    else:
        assert server.refused == 1 and (answer is None or "stalled" in answer["error"]), answer


def test_idle_connections_are_closed_after_the_header_deadline():
    """A connection that sends nothing is answered and closed after HEADER_TIMEOUT_S, whatever their number."""
    server = ThroughputServer("127.0.0.1", free_port()).start()
    idle = [_connect_from("127.0.0.1", server.port) for _ in range(5)]
    try:
        for conn in idle:
            conn.settimeout(HEADER_TIMEOUT_S + 5.0)
            answer = json.loads(conn.makefile("rb").readline())
            assert "no probe header" in answer["error"] and answer["error_kind"] == "server"
        assert server.open_connections == 0
    finally:
        server.stop()
        for conn in idle:
            conn.close()


# ---- the schedule goes on ------------------------------------------------------------------------------------

def test_the_probe_schedule_goes_on_after_a_probe_raises_or_a_server_answers_wrongly(tmp_path, hostile):
    """Once a server answering `{"sum_received": ""}` killed the master's probe thread for good, with nothing
    logged. Now a target out of range (a raise inside the probe) is a probe_failed record, a wrong answer a
    `server` failure, and the next round probes everyone again."""
    genuine = ThroughputServer("127.0.0.1", free_port()).start()
    junk = hostile(answer=b'{"sum_received": ""}\n')
    third_round = threading.Event()
    calls = {"n": 0}

    def targets():
        calls["n"] += 1
        if calls["n"] == 3:
            third_round.set()
        return [("bad", "127.0.0.1", 70000), ("junk", "127.0.0.1", junk.port), ("w", "127.0.0.1", genuine.port)]

    own = OwnState("m", "master", 1, 47.0, 8.0, 500.0, None, None, "", True)
    settings_ = ThroughputSection(probe=True, period_s=0.2, duration_s=0.1, interval_s=0.05)
    stop = threading.Event()
    try:
        with JsonlLog(tmp_path / "throughput.jsonl") as out:
            scheduler = ProbeScheduler(settings_, "m", targets, lambda: AgentSnapshot(0.0, own), out, stop).start()
            assert third_round.wait(60.0), "the schedule stopped"
            assert scheduler.alive
            stop.set()
            scheduler.join(10.0)
    finally:
        stop.set()
        genuine.stop()
    records = read_jsonl(tmp_path / "throughput.jsonl").records
    first_two = records[:6]
    assert [(r["kind"], r["server"]) for r in first_two] == [
        ("probe_failed", "bad"), ("throughput", "junk"), ("throughput", "w")] * 2
    assert "port must be" in first_two[0]["error"] and first_two[0]["port"] == 70000
    assert first_two[1]["error_kind"] == "server" and "sum_received" in first_two[1]["error"]
    assert first_two[2]["end"]["sum_received"]["bytes"] > 0 and "error" not in first_two[2]


def test_concurrent_probes_go_on_to_the_other_workers_while_one_probe_stalls(tmp_path, hostile):
    """In turn, a probe to a worker whose path stalls holds every other worker's probe for its length + the
    server's grace + the answer's margin (8 s here): no probe traffic at all in those seconds. With
    `concurrent`, each worker has its own schedule, so the genuine server is probed again and again while the
    stalled probe waits out its deadlines (as one iperf3 client per link would)."""
    genuine = ThroughputServer("127.0.0.1", free_port()).start()
    stalled = hostile(stall=True)
    own = OwnState("m", "master", 1, 47.0, 8.0, 500.0, None, None, "", True)
    settings_ = ThroughputSection(probe=True, period_s=0.2, duration_s=0.1, interval_s=0.05, concurrent=True)
    stop = threading.Event()
    targets = [("stalled", "127.0.0.1", stalled.port), ("w", "127.0.0.1", genuine.port)]
    try:
        with _WatchedLog(tmp_path / "throughput.jsonl") as out:
            scheduler = ProbeScheduler(settings_, "m", lambda: targets, lambda: AgentSnapshot(0.0, own), out,
                                       stop).start()
            assert out.third_genuine.wait(30.0), "the other worker's probes waited for the stalled one"
            stalled_ended_by_then = out.stalled_ended
            stop.set()
            scheduler.join(20.0)
            assert not scheduler.alive
    finally:
        stop.set()
        genuine.stop()
    assert stalled.stalled.is_set() and not stalled_ended_by_then
    ended = [r for r in read_jsonl(tmp_path / "throughput.jsonl").records if r.get("server") == "stalled"]
    assert ended and ended[0]["error_kind"] == "link"  # it ended by its deadline, logged as a link failure


def test_probes_begin_at_the_start_file_and_a_stop_before_it_ends_them(tmp_path):
    """With `start_file` (SITL's go, which the MPI job waits for too) the schedule asks for no target and sends
    nothing until the file exists, so the job's set-up has the air to itself; then it probes. Stopped before the
    go, it ends without a probe."""
    genuine = ThroughputServer("127.0.0.1", free_port()).start()
    own = OwnState("m", "master", 1, 47.0, 8.0, 500.0, None, None, "", True)
    go = tmp_path / "go"
    asked = threading.Event()

    def targets():
        asked.set()
        return [("w", "127.0.0.1", genuine.port)]

    settings_ = ThroughputSection(probe=True, period_s=0.2, duration_s=0.1, interval_s=0.05, concurrent=True,
                                  start_file=str(go))
    stop, never = threading.Event(), threading.Event()
    try:
        with _WatchedLog(tmp_path / "throughput.jsonl") as out:
            waiting = ProbeScheduler(settings_, "m", targets, lambda: AgentSnapshot(0.0, own), out, never).start()
            scheduler = ProbeScheduler(settings_, "m", targets, lambda: AgentSnapshot(0.0, own), out, stop).start()
            assert not asked.wait(1.0), "a schedule asked for its targets before the go"
            never.set()
            waiting.join(5.0)
            assert not waiting.alive, "stopped before the go, the schedule went on waiting"
            go.write_text("{}")
            assert out.third_genuine.wait(30.0), "no probes after the go"
            stop.set()
            scheduler.join(20.0)
    finally:
        stop.set()
        never.set()
        genuine.stop()
    records = read_jsonl(tmp_path / "throughput.jsonl").records
    assert records and all(r["server"] == "w" for r in records)
    assert records[0]["end"]["sum_received"]["bytes"] > 0


class _WatchedLog(JsonlLog):
    """The probe log, telling the test when the genuine server's third good probe is written."""

    def __init__(self, path):
        super().__init__(path)
        self.genuine, self.stalled_ended, self.third_genuine = 0, False, threading.Event()

    def write(self, kind, t_s=None, **fields):
        record = super().write(kind, t_s, **fields)
        if fields.get("server") == "stalled":
            self.stalled_ended = True
        elif fields.get("server") == "w" and "error" not in fields:
            self.genuine += 1
            if self.genuine == 3:
                self.third_genuine.set()
        return record


def test_a_sped_up_probe_waits_for_its_connection_and_its_answer_in_simulated_time(tmp_path, hostile):
    """A worker whose SYNs go unanswered (a listener whose accept queue is full drops them): at 4x the probe gives
    up after 3 simulated seconds, 0.75 s of wall time, as a real-time run gives up after 3 s. A server that takes
    the probe and never answers: at 4x the client gives up after the probe's length + GRACE_S + ANSWER_MARGIN_S
    of simulated time, 2.1 s of wall time, not 8.1. These waits were wall-clock at any speed-up, so a sped-up run
    logged a quarter as many failed probes per simulated minute. The bounds, 2.5 s and 5 s, sit well under the
    3 s and 8.1 s of unscaled waits, whatever the load adds."""
    listener = socket.create_server(("127.0.0.1", 0), backlog=0)
    port = listener.getsockname()[1]
    queued = socket.create_connection(("127.0.0.1", port), timeout=5.0)  # fills the accept queue
    own = OwnState("m", "master", 1, 47.0, 8.0, 500.0, None, None, "", True)
    settings_ = ThroughputSection(probe=True, period_s=1.0, duration_s=0.5, interval_s=0.1)
    try:
        with JsonlLog(tmp_path / "throughput.jsonl") as out:
            scheduler = ProbeScheduler(settings_, "m", lambda: [], lambda: AgentSnapshot(0.0, own), out,
                                       threading.Event(), clock=sped_up(4.0))
            started = time.monotonic()
            record = scheduler.probe_once("w", "127.0.0.1", port)
            waited_s = time.monotonic() - started
    finally:
        queued.close()
        listener.close()
    assert record["error_kind"] == "link" and "timed out" in record["error"], record
    assert waited_s < 2.5, waited_s
    stalled = hostile(stall=True)
    with JsonlLog(tmp_path / "throughput-2.jsonl") as out:
        scheduler = ProbeScheduler(settings_, "m", lambda: [], lambda: AgentSnapshot(0.0, own), out,
                                   threading.Event(), clock=sped_up(4.0))
        started = time.monotonic()
        record = scheduler.probe_once("w", "127.0.0.1", stalled.port)
        waited_s = time.monotonic() - started
    assert stalled.stalled.is_set() and record["error_kind"] == "link", record
    assert waited_s < 5.0, waited_s


def sped_up(speedup: float) -> Clock:
    """The run's clock at a fixed speed-up (its time axis is not read here)."""
    clock = Clock()
    clock.speedup = speedup
    return clock
