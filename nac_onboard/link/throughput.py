"""Throughput probes, iperf3-style: a TCP server on every vehicle and a client that measures one path.

One probe is one TCP connection. The client sends a JSON header line, then data for a fixed duration or byte
count, then half-closes; the server counts what arrives, per interval, and answers with its own measurement as a
JSON line. The result reads like `iperf3 -J` (DESIGN.md section 4): `start`, `intervals[]` (sender side, each
with `streams[]` and `sum`), `end.sum_sent` and `end.sum_received`, and the server's intervals under
`server_output_json`, the key iperf3 uses for `--get-server-output`. A failed probe is `{"error": "..."}` as in
iperf3, with `error_kind`: "link" (the path failed: no connection, a stall, a reset) or "server" (the server
refused the probe or answered nonsense), so a broken server is never read as a broken link. The receiver's figure
is the path's: the sender's also counts what still sits in its socket buffer.

The server takes anything from the network: the header is checked (type, range) before it is used, the header
must arrive within HEADER_TIMEOUT_S and the data within the probe's own length plus a grace, the answer has at
most MAX_INTERVALS intervals, and no connection can stop the server (a failure is logged and answered).
"""

from __future__ import annotations

import json
import logging
import mmap
import select
import socket
import struct
import threading
import time

from nac_onboard.errors import OperationFailed

log = logging.getLogger(__name__)

DEFAULT_PORT = 5201  # iperf3's
BLOCK_BYTES = 1024 * 1024  # per write: on a CPU-bound path (loopback) fewer, larger writes go faster
PACING_S = 0.005
RECV_BYTES = 1024 * 1024
MAX_ANSWER_BYTES = 1 << 20
HEADER_LIMIT_BYTES = 4096
HEADER_TIMEOUT_S = 2.0  # a client that connects and sends nothing holds the server this long at most
IDLE_TIMEOUT_S = 10.0
MAX_PROBE_S = 60.0  # the longest probe a server accepts (by duration; by bytes it must finish in this time too)
MAX_PROBE_BYTES = 10 ** 11
MIN_INTERVAL_S, MAX_INTERVALS = 0.05, 1200
GRACE_S = 5.0
PROTOCOL = "nac-probe/1"
LINK, SERVER = "link", "server"  # whose fault a failed probe is
# Fields of Linux's struct tcp_info (include/uapi/linux/tcp.h) that iperf3 reports, by byte offset.
_TCP_INFO = {"snd_mss": 16, "pmtu": 60, "rtt": 68, "rttvar": 72, "snd_cwnd": 80, "total_retrans": 100,
             "snd_wnd": 228}
_U32 = struct.Struct("=I")


class ProbeError(OperationFailed):
    """A probe could not run; the message names the peer and what went wrong, `kind` whose fault it is."""

    def __init__(self, message: str, kind: str = LINK):
        super().__init__(message)
        self.kind = kind


class HeaderError(ValueError):
    """A probe header the server refuses; the message says which field and what was expected."""


def check_header(line: bytes) -> dict:
    """The probe header as the server will use it: protocol, duration_s or bytes, interval_s, all in range."""
    try:
        header = json.loads(line, parse_constant=lambda c: c)  # NaN/Infinity come back as strings, refused below
    except (ValueError, UnicodeDecodeError, RecursionError):
        raise HeaderError("the probe header is not JSON") from None
    if not isinstance(header, dict):
        raise HeaderError("the probe header is not a JSON object")
    if header.get("protocol") != PROTOCOL:
        raise HeaderError(f"expected protocol {PROTOCOL}")
    duration_s, nbytes, interval_s = header.get("duration_s"), header.get("bytes"), header.get("interval_s", 0.5)
    if (duration_s is None) == (nbytes is None):
        raise HeaderError("give exactly one of duration_s and bytes")
    if duration_s is not None and not _number_within(duration_s, 0.0, MAX_PROBE_S, low_open=True):
        raise HeaderError(f"duration_s must be a number in (0, {MAX_PROBE_S:g}]")
    if nbytes is not None and (isinstance(nbytes, bool) or not isinstance(nbytes, int)
                               or not 0 < nbytes <= MAX_PROBE_BYTES):
        raise HeaderError(f"bytes must be an integer in 1..{MAX_PROBE_BYTES}")
    if not _number_within(interval_s, MIN_INTERVAL_S, MAX_PROBE_S):
        raise HeaderError(f"interval_s must be a number in [{MIN_INTERVAL_S:g}, {MAX_PROBE_S:g}]")
    return {"duration_s": duration_s, "bytes": nbytes, "interval_s": float(interval_s)}


def _number_within(value, low: float, high: float, low_open: bool = False) -> bool:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return (low < value if low_open else low <= value) and value <= high
    except OverflowError:
        return False


def tcp_info(sock: socket.socket) -> dict:
    """The sender's TCP state as iperf3 reports it (snd_cwnd in bytes, rtt in µs); {} where unavailable."""
    if not hasattr(socket, "TCP_INFO"):
        return {}
    try:
        raw = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 232)
    except OSError:
        return {}
    values = {name: _U32.unpack_from(raw, at)[0] for name, at in _TCP_INFO.items() if len(raw) >= at + 4}
    if "snd_cwnd" in values and "snd_mss" in values:
        values["snd_cwnd"] *= values["snd_mss"]  # packets -> bytes, as iperf3 does
    values.pop("snd_mss", None)
    return values


def total_retransmits(sock: socket.socket) -> int | None:
    return tcp_info(sock).get("total_retrans")


def interval_sum(start_s: float, end_s: float, nbytes: int, sender: bool, retransmits: int | None = None) -> dict:
    seconds = max(end_s - start_s, 0.0)
    out = {"start": round(start_s, 6), "end": round(end_s, 6), "seconds": round(seconds, 6), "bytes": nbytes,
           "bits_per_second": nbytes * 8 / seconds if seconds > 0 else 0.0, "omitted": False, "sender": sender}
    if sender:
        out["retransmits"] = retransmits if retransmits is not None else 0
    return out


class _IntervalCounter:
    """Bytes per reporting interval, relative to a start time. The hot loops keep the running total themselves
    and call close_interval only when the clock passes next_mark: a method call per block costs several percent
    of the rate on a fast path, and the loopback comparison with iperf3 (C) has to hold within 10 %."""

    def __init__(self, start_mono_s: float, interval_s: float, sender: bool, sock: socket.socket):
        self.t0, self.interval_s, self.sender, self.sock = start_mono_s, interval_s, sender, sock
        self.intervals: list[dict] = []
        self.mark_s, self.mark_bytes, self.total = 0.0, 0, 0
        self.next_mark = start_mono_s + interval_s
        self.retrans0 = self.retrans_mark = (total_retransmits(sock) or 0) if sender else 0

    def close_interval(self, now_mono_s: float, total: int) -> None:
        self.total = total
        self.next_mark = now_mono_s + self.interval_s
        end_s = now_mono_s - self.t0
        if end_s <= self.mark_s or len(self.intervals) >= MAX_INTERVALS:
            return
        retrans = None
        stream_extra = {}
        if self.sender:
            info = tcp_info(self.sock)
            now_retrans = info.pop("total_retrans", 0)
            retrans, self.retrans_mark = now_retrans - self.retrans_mark, now_retrans
            stream_extra = info
        s = interval_sum(self.mark_s, end_s, total - self.mark_bytes, self.sender, retrans)
        self.intervals.append({"streams": [dict(s, socket=self.sock.fileno(), **stream_extra)], "sum": s})
        self.mark_s, self.mark_bytes = end_s, total

    def retransmits(self) -> int:
        return (total_retransmits(self.sock) or 0) - self.retrans0 if self.sender else 0


def probe(host: str, port: int = DEFAULT_PORT, duration_s: float | None = 1.0, nbytes: int | None = None,
          interval_s: float = 0.5, rate_bps: float | None = None, connect_timeout_s: float = 3.0,
          block_bytes: int = BLOCK_BYTES) -> dict:
    """Send to a throughput server for duration_s (or nbytes) and return an iperf3-shaped result.

    rate_bps caps the sending rate (iperf3 -b) so a probe can share a link with other traffic.
    Raises ProbeError when the server cannot be reached or stops answering.
    """
    if (duration_s is None) == (nbytes is None):
        raise ValueError("give exactly one of duration_s and nbytes")
    if rate_bps:
        # paced writes of at most PACING_S worth of data: one 1 MiB burst would overshoot a slow cap many times over
        block_bytes = min(block_bytes, max(1024, int(rate_bps / 8 * PACING_S)))
    where = f"{host}:{port}"
    try:
        sock = socket.create_connection((host, port), timeout=connect_timeout_s)
    except OSError as err:
        raise ProbeError(f"cannot connect to throughput server {where}: {err.strerror or err}") from None
    with sock:
        header = {"protocol": PROTOCOL, "duration_s": duration_s, "bytes": nbytes, "interval_s": interval_s}
        local, remote = sock.getsockname(), sock.getpeername()
        started_unix_s = time.time()
        try:
            sock.sendall(json.dumps(header).encode() + b"\n")
            # Non-blocking writes, waiting in select() only when the buffer is full, as iperf3 does: Python's
            # own socket timeout costs a poll() per call, and a blocking write that waits for room for a whole
            # block both cost a good part of the rate on a fast path.
            sock.setblocking(False)
            t0 = time.monotonic()
            counter = _IntervalCounter(t0, interval_s, True, sock)
            _send_data(sock, counter, t0, duration_s, nbytes, rate_bps, block_bytes)
            t_end = time.monotonic()
            counter.close_interval(t_end, counter.total)
            sock.setblocking(True)
            set_kernel_timeouts(sock, send_s=IDLE_TIMEOUT_S, recv_s=IDLE_TIMEOUT_S)
            sock.shutdown(socket.SHUT_WR)
            server = _read_answer(sock, where)
        except (OSError, TimeoutError) as err:
            raise ProbeError(f"throughput probe to {where} failed: {err.strerror or err}", LINK) from None
    if not isinstance(server, dict) or "error" in server or not isinstance(server.get("sum_received"), dict):
        detail = server.get("error") if isinstance(server, dict) else None
        raise ProbeError(f"throughput server {where}: {detail or 'an answer without sum_received'}", SERVER)
    received = server["sum_received"]
    return {
        "start": {
            "connected": [{"socket": 1, "local_host": local[0], "local_port": local[1], "remote_host": remote[0],
                           "remote_port": remote[1]}],
            "timestamp": {"timesecs": int(started_unix_s), "time_s": started_unix_s},
            "test_start": {"protocol": "TCP", "num_streams": 1, "blksize": block_bytes, "duration": duration_s or 0,
                           "bytes": nbytes or 0, "rate_bps": rate_bps or 0},
        },
        "intervals": counter.intervals,
        "end": {
            "sum_sent": interval_sum(0.0, t_end - t0, counter.total, True, counter.retransmits()),
            "sum_received": interval_sum(received["start"], received["end"], received["bytes"], False),
        },
        "server_output_json": {"intervals": server.get("intervals", [])},
    }


def _send_data(sock, counter: _IntervalCounter, t0: float, duration_s, nbytes, rate_bps, block_bytes) -> None:
    block = memoryview(mmap.mmap(-1, block_bytes))  # page-aligned, as iperf3's: copies run faster
    deadline = t0 + duration_s if duration_s is not None else float("inf")
    limit = nbytes if nbytes is not None else float("inf")
    send, monotonic, total, now = sock.send, time.monotonic, 0, t0
    while now < deadline and total < limit:
        if rate_bps:
            # a block leaves when the time to send it at rate_bps has passed, not before: sent first and paced
            # after, N blocks would reach the receiver in N - 1 block times (11 % high for a 10-block probe)
            ahead_s = (total + min(block_bytes, limit - total)) * 8 / rate_bps - (now - t0)
            if ahead_s > 0:
                time.sleep(min(ahead_s, deadline - now))
                now = monotonic()
                continue
        try:
            total += send(block if limit - total >= block_bytes else block[:int(limit - total)])
        except BlockingIOError:  # the send buffer is full: wait for room, never past the deadline
            if not select.select([], [sock], [], min(deadline - now, IDLE_TIMEOUT_S))[1] and duration_s is None:
                raise TimeoutError(f"the receiver took nothing for {IDLE_TIMEOUT_S:g} s") from None
        now = monotonic()
        if now >= counter.next_mark:
            counter.close_interval(now, total)
    counter.total = total


def set_kernel_timeouts(sock: socket.socket, send_s: float, recv_s: float) -> None:
    for option, seconds in ((socket.SO_SNDTIMEO, send_s), (socket.SO_RCVTIMEO, recv_s)):
        sock.setsockopt(socket.SOL_SOCKET, option, struct.pack("ll", int(seconds), int(seconds % 1 * 1e6)))


def _read_answer(sock: socket.socket, where: str) -> dict:
    data = b""
    while not data.endswith(b"\n"):
        try:
            chunk = sock.recv(65536)
        except BlockingIOError:
            raise TimeoutError(f"no result within {IDLE_TIMEOUT_S:g} s") from None
        if not chunk:
            break
        data += chunk
        if len(data) > MAX_ANSWER_BYTES:
            raise ProbeError(f"throughput server {where}: an answer over {MAX_ANSWER_BYTES} bytes", SERVER)
    try:
        return json.loads(data)
    except (ValueError, RecursionError):
        raise ProbeError(f"throughput server {where} gave no result (is it a NAC throughput server?)",
                         SERVER) from None


class ThroughputServer:
    """Accepts probes on a TCP port, one at a time, in a background thread (or serve_forever); stop() closes it."""

    def __init__(self, bind: str = "127.0.0.1", port: int = DEFAULT_PORT):
        self.sock = socket.create_server((bind, port), reuse_port=False)
        self.port = self.sock.getsockname()[1]
        self.refused = 0  # probes refused or broken off, by the server's checks
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="throughput-server", daemon=True)

    def start(self) -> ThroughputServer:
        self._thread.start()
        return self

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self) -> None:
        self._stop.set()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        self._thread.join(timeout=2.0)

    def serve_forever(self) -> None:
        self._serve()

    def _serve(self) -> None:
        try:
            self.sock.settimeout(0.5)
        except OSError:
            return  # stopped before it started
        while not self._stop.is_set():
            try:
                conn, addr = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            # One probe at a time, as iperf3's server: concurrent probes would measure each other, and a receiver
            # in its own thread runs measurably slower on a fast path. Others wait in the listen backlog.
            try:
                self._handle(conn, addr)
            except Exception:  # a connection must never stop the server: the agent would log every probe as lost
                self.refused += 1
                log.exception("throughput probe from %s:%s", addr[0], addr[1])

    def _handle(self, conn: socket.socket, addr) -> None:
        with conn:
            try:
                answer = receive_probe(conn)
            except (OSError, TimeoutError, HeaderError) as err:
                self.refused += 1
                log.warning("throughput probe from %s:%s refused: %s", addr[0], addr[1], err)
                try:
                    conn.settimeout(1.0)
                    conn.sendall(json.dumps({"error": str(err)}).encode() + b"\n")
                except OSError:
                    pass
                return
            try:
                conn.sendall(json.dumps(answer).encode() + b"\n")
            except OSError as err:
                log.warning("could not answer the probe from %s:%s: %s", addr[0], addr[1], err)


def _read_header(conn: socket.socket) -> tuple[bytes, bytes]:
    """The header line and what came after it, within HEADER_TIMEOUT_S in all."""
    deadline = time.monotonic() + HEADER_TIMEOUT_S
    header_bytes = b""
    while b"\n" not in header_bytes:
        left_s = deadline - time.monotonic()
        if left_s <= 0:
            raise TimeoutError(f"no probe header within {HEADER_TIMEOUT_S:g} s")
        conn.settimeout(left_s)
        try:
            chunk = conn.recv(HEADER_LIMIT_BYTES - len(header_bytes))
        except TimeoutError:
            raise TimeoutError(f"no probe header within {HEADER_TIMEOUT_S:g} s") from None
        if not chunk:
            raise HeaderError("connection closed before the probe header")
        header_bytes += chunk
        if b"\n" not in header_bytes and len(header_bytes) >= HEADER_LIMIT_BYTES:
            raise HeaderError("probe header too long")
    line, _, rest = header_bytes.partition(b"\n")
    return line, rest


def receive_probe(conn: socket.socket) -> dict:
    """Read one probe's header and data until the sender half-closes; the receiver's measurement."""
    line, rest = _read_header(conn)
    header = check_header(line)
    t0 = time.monotonic()
    ends_by = t0 + (header["duration_s"] or MAX_PROBE_S) + GRACE_S
    counter = _IntervalCounter(t0, header["interval_s"], False, conn)
    buf = mmap.mmap(-1, RECV_BYTES)
    conn.settimeout(None)
    set_kernel_timeouts(conn, send_s=IDLE_TIMEOUT_S, recv_s=IDLE_TIMEOUT_S)
    recv_into, monotonic = conn.recv_into, time.monotonic
    total, last_s = len(rest), t0
    while True:
        try:
            n = recv_into(buf)
        except BlockingIOError:
            raise TimeoutError(f"the sender went silent for {IDLE_TIMEOUT_S:g} s") from None
        if n == 0:
            break
        total += n
        last_s = monotonic()
        if last_s >= counter.next_mark:
            if last_s > ends_by:
                raise TimeoutError("the sender kept sending past the probe's length")
            counter.close_interval(last_s, total)
    counter.close_interval(last_s, total)
    return {"sum_received": interval_sum(0.0, last_s - t0, total, False), "intervals": counter.intervals}
