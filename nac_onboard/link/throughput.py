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
must arrive within HEADER_TIMEOUT_S and the data within the probe's own length plus GRACE_S (a probe is cut
there), the answer has at most MAX_INTERVALS intervals, and no connection can stop the server (a failure is
logged and answered). Connections are accepted at once and capped per source address and in all (see
ThroughputServer), so idle or trickling connections cannot keep a genuine probe out. The client takes the
server's answer as hostile too: every field is checked (type, finite, non-negative, within the probe's length and
what was sent) and the result is rebuilt from checked values only, so it never holds NaN or Infinity; every wait
of the client has a deadline. A failure is "link" when nothing (more) got through: no connection, a reset, no
answer in time, or the server saying the data stopped coming (a one-way blackhole); "server" when the server
refused the probe or its answer was wrong.
"""

from __future__ import annotations

import json
import logging
import mmap
import select
import selectors
import socket
import struct
import threading
import time
from collections.abc import Callable

from nac_onboard.clock import Clock, slowed_s
from nac_onboard.errors import OperationFailed

log = logging.getLogger(__name__)

DEFAULT_PORT = 5201  # iperf3's
BLOCK_BYTES = 1024 * 1024  # per write: on a CPU-bound path (loopback) fewer, larger writes go faster
PACING_S = 0.005
RECV_BYTES = 1024 * 1024
MAX_ANSWER_BYTES = 1 << 20
HEADER_LIMIT_BYTES = 4096
HEADER_TIMEOUT_S = 2.0  # a client that connects and sends nothing holds the server this long at most
IDLE_TIMEOUT_S = 10.0  # the run's seconds below 1x (slowed_s): a slowed run's link carries its bytes that slowly
MAX_PROBE_S = 60.0  # the longest probe a server accepts (by duration; by bytes it must finish in this time too)
MAX_PROBE_BYTES = 10 ** 11
MIN_INTERVAL_S, MAX_INTERVALS = 0.05, 1200
GRACE_S = 5.0  # a probe is cut at its length + GRACE_S
ANSWER_MARGIN_S = 3.0  # the client waits for the answer until the server's cut + this
STALLED_S = 1.0  # a probe cut at its end after this long without data had stalled: a link failure
MAX_RATE_BPS = 1e12
LISTEN_BACKLOG = 128
TICK_S = 0.25  # the accepting thread's longest sleep: deadlines are kept to this
MAX_PENDING_PER_SOURCE, MAX_PENDING = 8, 64  # connections still without their header, per address and in all
MAX_PROBES_PER_SOURCE, MAX_PROBES = 2, 8  # probes being received, per address and in all
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
    seconds = round(max(end_s - start_s, 0.0), 6)  # rounded before dividing: 1e-300 s would give an infinite rate
    out = {"start": round(start_s, 6), "end": round(end_s, 6), "seconds": seconds, "bytes": nbytes,
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


def check_probe_arguments(port: int, duration_s, nbytes, interval_s, rate_bps) -> None:
    """A probe's own settings, before anything is sent: ValueError naming the field and the range expected."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ValueError(f"port must be an integer in 1..65535, not {port!r}")
    if (duration_s is None) == (nbytes is None):
        raise ValueError("give exactly one of duration_s and nbytes")
    if duration_s is not None and not _number_within(duration_s, 0.0, MAX_PROBE_S, low_open=True):
        raise ValueError(f"duration_s must be a number in (0, {MAX_PROBE_S:g}], not {duration_s!r}")
    if nbytes is not None and (isinstance(nbytes, bool) or not isinstance(nbytes, int)
                               or not 0 < nbytes <= MAX_PROBE_BYTES):
        raise ValueError(f"nbytes must be an integer in 1..{MAX_PROBE_BYTES}, not {nbytes!r}")
    if not _number_within(interval_s, MIN_INTERVAL_S, MAX_PROBE_S):
        raise ValueError(f"interval_s must be a number in [{MIN_INTERVAL_S:g}, {MAX_PROBE_S:g}], not {interval_s!r}")
    if rate_bps is not None and not _number_within(rate_bps, 0.0, MAX_RATE_BPS, low_open=True):
        raise ValueError(f"rate_bps must be a number in (0, {MAX_RATE_BPS:g}], not {rate_bps!r}")


def probe(host: str, port: int = DEFAULT_PORT, duration_s: float | None = 1.0, nbytes: int | None = None,
          interval_s: float = 0.5, rate_bps: float | None = None, connect_timeout_s: float = 3.0,
          block_bytes: int = BLOCK_BYTES, grace_s: float = GRACE_S, answer_margin_s: float = ANSWER_MARGIN_S,
          started: Callable[[socket.socket], None] | None = None, idle_timeout_s: float = IDLE_TIMEOUT_S) -> dict:
    """Send to a throughput server for duration_s (or nbytes) and return an iperf3-shaped result.

    rate_bps caps the sending rate (iperf3 -b) so a probe can share a link with other traffic. started, if given,
    is handed the connected socket: shutting it down from another thread ends the probe at once (a ProbeError).
    Raises ValueError for settings out of range (before connecting), ProbeError when the probe fails: kind LINK
    when nothing (more) got through (no connection, a reset, a stall, no answer in time, or the server saying its
    data stopped), SERVER when the server refused the probe or its answer is not a measurement (checked field by
    field: types, finite, non-negative, within the probe's length and what was sent). Every wait has a deadline.
    """
    check_probe_arguments(port, duration_s, nbytes, interval_s, rate_bps)
    if rate_bps:
        # paced writes of at most PACING_S worth of data: one 1 MiB burst would overshoot a slow cap many times over
        block_bytes = min(block_bytes, max(1024, int(rate_bps / 8 * PACING_S)))
    where = f"{host}:{port}"
    try:
        sock = socket.create_connection((host, port), timeout=connect_timeout_s)
    except OSError as err:
        raise ProbeError(f"cannot connect to throughput server {where}: {err.strerror or err}") from None
    if started is not None:
        started(sock)
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
            _send_data(sock, counter, t0, duration_s, nbytes, rate_bps, block_bytes, idle_timeout_s)
            t_end = time.monotonic()
            counter.close_interval(t_end, counter.total)
            sock.shutdown(socket.SHUT_WR)
            # the server answers by the probe's length + GRACE_S from its start (it cuts the probe there)
            answer_by = t0 + (duration_s or MAX_PROBE_S) + grace_s + answer_margin_s
            raw = _read_answer(sock, where, max(answer_by, time.monotonic() + answer_margin_s))
        except (OSError, TimeoutError) as err:
            raise ProbeError(f"throughput probe to {where} failed: {err.strerror or err}", LINK) from None
    max_end_s = (duration_s or MAX_PROBE_S) + grace_s + answer_margin_s
    received, server_intervals = check_answer(raw, where, counter.total, max_end_s)
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
            "sum_received": received,
        },
        "server_output_json": {"intervals": server_intervals},
    }


def _printable(text: str, limit: int = 300) -> str:
    """A server's text as it may appear in a record or on a terminal: printable characters, bounded length."""
    text = "".join(c if c.isprintable() else "?" for c in text[:limit])
    return text + ("..." if len(text) >= limit else "")


def _answer_number(value, what: str, where: str, high: float, integer: bool = False):
    """A number of the server's answer: the right type, finite, in [0, high]; else a ProbeError (SERVER)."""
    ok = not isinstance(value, bool) and (isinstance(value, int) if integer else isinstance(value, (int, float)))
    if not ok or not _number_within(value, 0.0, high):
        expected = "an integer" if integer else "a number"
        raise ProbeError(f"throughput server {where}: {what} is {_printable(repr(value), 60)}, expected {expected} "
                         f"in 0..{high:g}", SERVER)
    return value


def check_answer(raw: bytes, where: str, sent_bytes: int, max_end_s: float) -> tuple[dict, list[dict]]:
    """The server's answer line as the probe's sum_received and the server's intervals, rebuilt from checked
    values only: `sum_received` and each interval's `sum` need `start` <= `end` in [0, max_end_s] and `bytes`
    an integer in 0..sent_bytes (a receiver cannot count more than was sent); at most MAX_INTERVALS intervals,
    their bytes adding up to at most sum_received's. Raises ProbeError: SERVER for a wrong answer or a refusal,
    LINK when the server says the data stopped coming (its `error_kind`)."""
    try:
        answer = json.loads(raw, parse_constant=lambda c: c)  # NaN/Infinity come back as strings, refused below
    except (ValueError, UnicodeDecodeError, RecursionError):
        if not raw.strip():
            raise ProbeError(f"throughput server {where} closed without an answer", SERVER) from None
        raise ProbeError(f"throughput server {where} gave no result (is it a NAC throughput server?)",
                         SERVER) from None
    if not isinstance(answer, dict):
        raise ProbeError(f"throughput server {where}: the answer is not a JSON object", SERVER)
    if "error" in answer:
        message = answer["error"] if isinstance(answer["error"], str) else repr(answer["error"])
        kind = LINK if answer.get("error_kind") == LINK else SERVER
        raise ProbeError(f"throughput server {where}: {_printable(message)}", kind)
    received = answer.get("sum_received")
    if not isinstance(received, dict):
        raise ProbeError(f"throughput server {where}: an answer without a sum_received object", SERVER)
    summary = _checked_interval(received, "sum_received", where, sent_bytes, max_end_s)
    intervals = answer.get("intervals", [])
    if not isinstance(intervals, list) or len(intervals) > MAX_INTERVALS:
        raise ProbeError(f"throughput server {where}: intervals must be a list of at most {MAX_INTERVALS}", SERVER)
    rebuilt = []
    for n, interval in enumerate(intervals):
        s = interval.get("sum") if isinstance(interval, dict) else None
        if not isinstance(s, dict):
            raise ProbeError(f"throughput server {where}: intervals[{n}] has no sum object", SERVER)
        checked = _checked_interval(s, f"intervals[{n}].sum", where, summary["bytes"], max_end_s)
        rebuilt.append({"streams": [dict(checked)], "sum": checked})
    if sum(i["sum"]["bytes"] for i in rebuilt) > summary["bytes"]:
        raise ProbeError(f"throughput server {where}: its intervals add up to more bytes than sum_received",
                         SERVER)
    return summary, rebuilt


def _checked_interval(value: dict, what: str, where: str, max_bytes: int, max_end_s: float) -> dict:
    start_s = _answer_number(value.get("start"), f"{what}.start", where, max_end_s)
    end_s = _answer_number(value.get("end"), f"{what}.end", where, max_end_s)
    nbytes = _answer_number(value.get("bytes"), f"{what}.bytes", where, max_bytes, integer=True)
    if end_s < start_s:
        raise ProbeError(f"throughput server {where}: {what} ends ({end_s:g}) before it starts ({start_s:g})",
                         SERVER)
    return interval_sum(float(start_s), float(end_s), nbytes, False)


def _send_data(sock, counter: _IntervalCounter, t0: float, duration_s, nbytes, rate_bps, block_bytes,
               idle_timeout_s: float) -> None:
    block = memoryview(mmap.mmap(-1, block_bytes))  # page-aligned, as iperf3's: copies run faster
    deadline = t0 + (duration_s if duration_s is not None else MAX_PROBE_S)  # by bytes: the server's limit
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
            if not select.select([], [sock], [], min(deadline - now, idle_timeout_s))[1] and duration_s is None:
                raise TimeoutError(f"the receiver took nothing for {idle_timeout_s:g} s") from None
        now = monotonic()
        if now >= counter.next_mark:
            counter.close_interval(now, total)
    counter.total = total
    if nbytes is not None and total < nbytes:
        raise TimeoutError(f"could not send {nbytes} bytes within {MAX_PROBE_S:g} s: the path is too slow")


def set_kernel_timeouts(sock: socket.socket, send_s: float, recv_s: float) -> None:
    for option, seconds in ((socket.SO_SNDTIMEO, send_s), (socket.SO_RCVTIMEO, recv_s)):
        sock.setsockopt(socket.SOL_SOCKET, option, struct.pack("ll", int(seconds), int(seconds % 1 * 1e6)))


def _read_answer(sock: socket.socket, where: str, deadline_mono_s: float) -> bytes:
    """The server's answer line (up to MAX_ANSWER_BYTES), by deadline_mono_s: a server that says nothing, or
    trickles its answer, is given up on then (TimeoutError: nothing more got through)."""
    data = b""
    while not data.endswith(b"\n"):
        left_s = deadline_mono_s - time.monotonic()
        if left_s <= 0 or not select.select([sock], [], [], left_s)[0]:
            raise TimeoutError("no answer from the server in time: the path stalled") from None
        try:
            chunk = sock.recv(65536)
        except BlockingIOError:
            continue
        if not chunk:
            break
        data += chunk
        if len(data) > MAX_ANSWER_BYTES:
            raise ProbeError(f"throughput server {where}: an answer over {MAX_ANSWER_BYTES} bytes", SERVER)
    return data


class _Pending:
    """A connection whose header has not all arrived; it has until deadline_mono_s."""

    __slots__ = ("conn", "addr", "deadline_mono_s", "data")

    def __init__(self, conn: socket.socket, addr, deadline_mono_s: float):
        self.conn, self.addr, self.deadline_mono_s, self.data = conn, addr, deadline_mono_s, b""


class _Probe:
    """A probe being received in its own thread; the accepting thread cuts it (cut()) at its deadline."""

    def __init__(self, conn: socket.socket, addr, ends_by_mono_s: float):
        self.conn, self.addr, self.ends_by_mono_s = conn, addr, ends_by_mono_s
        self.cut_reason: str | None = None

    def cut(self, reason: str) -> None:
        if self.cut_reason is None:
            self.cut_reason = reason
            try:
                self.conn.shutdown(socket.SHUT_RD)  # the receiving thread's recv returns at once
            except OSError:
                pass


class ThroughputServer:
    """Accepts probes on a TCP port in a background thread (or serve_forever); stop() closes it.

    One thread accepts every connection at once (the listen backlog never fills) and reads headers without
    blocking; a connection has HEADER_TIMEOUT_S for its header. At most MAX_PENDING_PER_SOURCE header-less
    connections per source address and MAX_PENDING in all are kept: over that, the oldest of the source (or of the
    source holding the most) is closed, so idle connections cannot crowd out a probe that sends its header as it
    connects. A probe with a valid header is received in its own thread, at most MAX_PROBES_PER_SOURCE per
    address and MAX_PROBES in all (over that, the oldest probe of the address holding the most is cut, if it holds
    more than the newcomer's address; else the newcomer is refused), and is cut at its length + GRACE_S.
    """

    def __init__(self, bind: str = "127.0.0.1", port: int = DEFAULT_PORT, clock: Clock | None = None):
        self.sock = socket.create_server((bind, port), reuse_port=False, backlog=LISTEN_BACKLOG)
        self.clock = clock or Clock()  # GRACE_S is the run's time: a sped-up run's probes are cut as soon in it
        self.port = self.sock.getsockname()[1]
        self.refused = 0  # probes refused or broken off, by the server's checks
        self.shed = 0  # connections closed over the caps, before their header
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._pending: dict[socket.socket, _Pending] = {}  # in arrival order
        self._probes: list[_Probe] = []  # in start order
        self._thread = threading.Thread(target=self._serve, name="throughput-server", daemon=True)

    def start(self) -> ThroughputServer:
        self._thread.start()
        return self

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def open_connections(self) -> int:
        """Connections the server holds now: awaiting their header, or being received."""
        with self._lock:
            return len(self._pending) + len(self._probes)

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self.sock.close()

    def serve_forever(self) -> None:
        self._serve()

    def _serve(self) -> None:
        selector = selectors.DefaultSelector()
        try:
            self.sock.setblocking(False)
            selector.register(self.sock, selectors.EVENT_READ)
        except (OSError, ValueError):
            selector.close()
            return  # stopped before it started
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                wait_s = min([TICK_S] + [p.deadline_mono_s - now for p in self._pending.values()])
                for key, _ in selector.select(max(wait_s, 0.0)):
                    if key.fileobj is self.sock:
                        self._accept_all(selector)
                    else:
                        self._guarded(self._read_header, selector, key.data)
                self._expire(selector, time.monotonic())
        finally:
            with self._lock:
                pending, probes = list(self._pending.values()), list(self._probes)
                self._pending.clear()
            for p in pending:
                p.conn.close()
            for pr in probes:
                pr.cut("the server is stopping")
            selector.close()

    def _guarded(self, handler, *args) -> None:
        """A connection must never stop the server: the agent would log every probe as lost."""
        try:
            handler(*args)
        except Exception:
            self.refused += 1
            log.exception("throughput server: a connection failed")

    def _accept_all(self, selector) -> None:
        for _ in range(LISTEN_BACKLOG):
            try:
                conn, addr = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as err:  # EMFILE and the like: the connection stays queued, we try again next tick
                log.warning("throughput server cannot accept: %s", err)
                return
            self._guarded(self._admit, selector, conn, addr)

    def _admit(self, selector, conn: socket.socket, addr) -> None:
        conn.setblocking(False)
        with self._lock:
            same = [p for p in self._pending.values() if p.addr[0] == addr[0]]
            if len(same) >= MAX_PENDING_PER_SOURCE:
                self._shed(selector, same[0])
            elif len(self._pending) >= MAX_PENDING:
                by_source: dict[str, list[_Pending]] = {}
                for p in self._pending.values():
                    by_source.setdefault(p.addr[0], []).append(p)
                self._shed(selector, max(by_source.values(), key=len)[0])
            pending = _Pending(conn, addr, time.monotonic() + HEADER_TIMEOUT_S)
            self._pending[conn] = pending
        selector.register(conn, selectors.EVENT_READ, pending)

    def _shed(self, selector, pending: _Pending) -> None:
        """Close a header-less connection at once, over the caps (the lock is held)."""
        del self._pending[pending.conn]
        selector.unregister(pending.conn)
        pending.conn.close()
        self.shed += 1

    def _drop(self, selector, pending: _Pending) -> None:
        with self._lock:
            self._pending.pop(pending.conn, None)
        try:
            selector.unregister(pending.conn)
        except (KeyError, ValueError):
            pass

    def _expire(self, selector, now: float) -> None:
        for p in [p for p in self._pending.values() if p.deadline_mono_s <= now]:
            self._drop(selector, p)
            self._refuse(p.conn, p.addr, f"no probe header within {HEADER_TIMEOUT_S:g} s")
        with self._lock:
            late = [pr for pr in self._probes if pr.ends_by_mono_s <= now]
        for pr in late:
            pr.cut(f"the probe ran past its length + {GRACE_S:g} s")

    def _read_header(self, selector, pending: _Pending) -> None:
        try:
            chunk = pending.conn.recv(HEADER_LIMIT_BYTES - len(pending.data))
        except (BlockingIOError, InterruptedError):
            return
        except OSError as err:
            self._drop(selector, pending)
            pending.conn.close()
            log.info("throughput connection from %s:%s lost before its header: %s", *pending.addr[:2], err)
            return
        if not chunk:
            self._drop(selector, pending)
            self._refuse(pending.conn, pending.addr, "connection closed before the probe header")
            return
        pending.data += chunk
        if b"\n" not in pending.data:
            if len(pending.data) >= HEADER_LIMIT_BYTES:
                self._drop(selector, pending)
                self._refuse(pending.conn, pending.addr, "probe header too long")
            return
        self._drop(selector, pending)
        line, _, rest = pending.data.partition(b"\n")
        try:
            header = check_header(line)
        except HeaderError as err:
            self._refuse(pending.conn, pending.addr, str(err))
            return
        self._start_probe(pending.conn, pending.addr, header, rest)

    def _start_probe(self, conn: socket.socket, addr, header: dict, rest: bytes) -> None:
        source = addr[0]
        with self._lock:
            mine = sum(1 for pr in self._probes if pr.addr[0] == source)
            busy = None
            if mine >= MAX_PROBES_PER_SOURCE:
                busy = f"busy: {mine} probes from {source} in progress"
            elif len(self._probes) >= MAX_PROBES:
                by_source: dict[str, list[_Probe]] = {}
                for pr in self._probes:
                    by_source.setdefault(pr.addr[0], []).append(pr)
                heaviest = max(by_source.values(), key=len)
                if len(heaviest) > mine + 1:
                    heaviest[0].cut("cut to serve a probe from another address")
                    self._probes.remove(heaviest[0])
                else:
                    busy = f"busy: {len(self._probes)} probes in progress"
            if busy is None:
                t0 = time.monotonic()
                probe_ = _Probe(conn, addr, t0 + (header["duration_s"] or MAX_PROBE_S) + self.clock.wall_s(GRACE_S))
                self._probes.append(probe_)
        if busy is not None:
            self._refuse(conn, addr, busy)
            return
        threading.Thread(target=self._run_probe, args=(probe_, header, rest, t0), daemon=True,
                         name=f"throughput-probe-{addr[0]}:{addr[1]}").start()

    def _refuse(self, conn: socket.socket, addr, message: str, kind: str = SERVER) -> None:
        """Answer {"error", "error_kind"} if the socket takes it at once (never waits), then close."""
        self.refused += 1
        log.warning("throughput probe from %s:%s refused: %s", addr[0], addr[1], message)
        with conn:
            try:
                conn.setblocking(False)
                conn.send(json.dumps({"error": message, "error_kind": kind}).encode() + b"\n")
                conn.shutdown(socket.SHUT_WR)
            except OSError:
                pass

    def _run_probe(self, probe_: _Probe, header: dict, rest: bytes, t0: float) -> None:
        conn, addr = probe_.conn, probe_.addr
        try:
            with conn:
                try:
                    answer = _receive_data(conn, header, rest, t0, probe_, self.clock.speedup)
                except _ProbeBroken as err:
                    self._refuse(conn, addr, str(err), err.kind)
                    return
                try:
                    conn.sendall(json.dumps(answer, allow_nan=False).encode() + b"\n")
                except OSError as err:
                    log.warning("could not answer the probe from %s:%s: %s", addr[0], addr[1], err)
        except Exception:
            self.refused += 1
            log.exception("throughput probe from %s:%s", addr[0], addr[1])
        finally:
            with self._lock:
                if probe_ in self._probes:
                    self._probes.remove(probe_)


class _ProbeBroken(Exception):
    """A probe the server stops receiving; kind says whose fault (LINK: the data stopped coming)."""

    def __init__(self, message: str, kind: str):
        super().__init__(message)
        self.kind = kind


def _receive_data(conn: socket.socket, header: dict, rest: bytes, t0: float, probe_: _Probe, speedup: float) -> dict:
    """Count one probe's data until the sender half-closes; the receiver's measurement. Raises _ProbeBroken. Its
    stall limits are the run's seconds below 1x (at 0.1x, 10 wall seconds without data were 1 simulated second,
    and a slowed air's full queue holds more: probes were refused as stalled)."""
    idle_s, stalled_s = slowed_s(IDLE_TIMEOUT_S, speedup), slowed_s(STALLED_S, speedup)
    counter = _IntervalCounter(t0, header["interval_s"], False, conn)
    buf = mmap.mmap(-1, RECV_BYTES)
    conn.setblocking(True)
    set_kernel_timeouts(conn, send_s=idle_s, recv_s=idle_s)
    recv_into, monotonic = conn.recv_into, time.monotonic
    total, last_s = len(rest), t0
    try:
        while True:
            try:
                n = recv_into(buf)
            except BlockingIOError:
                raise _ProbeBroken(f"no data for {IDLE_TIMEOUT_S:g} s: the path stalled", LINK) from None
            if n == 0:
                break
            total += n
            last_s = monotonic()
            if last_s >= counter.next_mark:
                counter.close_interval(last_s, total)
    except OSError as err:  # a reset: the path (or the sender) broke it off
        raise _ProbeBroken(f"the connection broke: {err.strerror or err}", LINK) from None
    if probe_.cut_reason is not None:
        silent_s = monotonic() - last_s
        if silent_s >= stalled_s:  # bytes had stopped flowing: the link failed, not the sender
            raise _ProbeBroken(f"no data for the last {silent_s * min(speedup, 1.0):.1f} s of the probe: the path "
                               "stalled", LINK)
        raise _ProbeBroken(probe_.cut_reason, SERVER)
    counter.close_interval(last_s, total)
    return {"sum_received": interval_sum(0.0, last_s - t0, total, False), "intervals": counter.intervals}
