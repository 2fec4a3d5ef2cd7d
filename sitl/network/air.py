"""The air: one network namespace per simulated companion computer, each with an address on a bridge that lives
in a namespace of its own, as each Jetson is its own host on the Wi-Fi.

    <prefix>-air   bridge `air` and one port per station (veth `<tag>p<i>`)
    <prefix>-<i>   station i: `lo` and `air0` (10.<x>.0.<i+1>/16), joined to its port

Deleting the namespaces removes every veth, the bridge, the qdiscs and the nftables table with them, so close()
is one loop, and a run killed before it ran leaves only namespaces that the next run removes (netns.PREFIX).
`tc` and `nft` run as long-lived batch processes fed one line per change, so a shaping update costs a write, not a
process start.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from nac_onboard.child_process import die_with_parent_preexec
from sitl.network import netns
from sitl.network.shaping import AirState, Layout

log = logging.getLogger(__name__)
AIR_PREFIX_LENGTH = 16  # each run's stations share one 10.<x>.0.0/16
MAX_STATIONS = 250
NFT_TABLE = "nacair"
CARRIER_TIMEOUT_S = 5.0
CARRIER_POLL_S = 0.02  # a carrier comes within microseconds of a successful set up: polled, not awaited
TCP_RTO_MIN_US, TCP_RTO_MAX_MS = 200_000, 120_000  # Linux's defaults
CONGESTION_CONTROL_PROC = Path("/proc/sys/net/ipv4")


def allow_congestion_control(name: str) -> bool:
    """Whether station namespaces can default to `name`: Linux lets a namespace other than the host's default only
    to an algorithm on the host's allowed list (tcp_set_default_congestion_control), so it is added there if the
    kernel has it. The list only permits: no socket's algorithm changes, the host's default stays."""
    try:
        available = (CONGESTION_CONTROL_PROC / "tcp_available_congestion_control").read_text().split()
        allowed_path = CONGESTION_CONTROL_PROC / "tcp_allowed_congestion_control"
        allowed = allowed_path.read_text().split()
        if name in allowed:
            return True
        if name not in available:
            log.warning("this kernel has no %s congestion control: the companions' TCP is this host's default", name)
            return False
        allowed_path.write_text(" ".join([*allowed, name]) + "\n")
        log.info("added %s to the host's allowed TCP congestion controls (the companions' default)", name)
        return True
    except OSError as err:
        log.warning("cannot give the companions %s congestion control (%s): their TCP is this host's default", name,
                    err)
        return False


class CommandStream:
    """A long-lived `tc -batch -` or `nft -i` fed lines; what it prints on stderr goes to the log."""

    def __init__(self, command: list[str], what: str):
        self.what = what
        self.errors = 0
        self.proc = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True, bufsize=1, preexec_fn=die_with_parent_preexec())
        self._reader = threading.Thread(target=self._read_errors, name=f"{what}-stderr", daemon=True)
        self._reader.start()

    def _read_errors(self) -> None:
        for line in self.proc.stderr:
            if line.strip() and not line.startswith("Warning"):
                self.errors += 1
                log.warning("%s: %s", self.what, line.strip())

    def send(self, text: str) -> None:
        if self.proc.poll() is not None:
            raise netns.NetworkError(f"{self.what} stopped (exit code {self.proc.returncode})")
        try:
            self.proc.stdin.write(text if text.endswith("\n") else text + "\n")
            self.proc.stdin.flush()
        except (OSError, ValueError) as err:  # a broken pipe; a closed one (the network is being removed)
            raise netns.NetworkError(f"{self.what}: {err}") from None

    def abandon(self) -> None:
        """Ended without applying what it still holds, its namespace about to be deleted: `nft -i` spends a
        second of CPU after the end of its input (1.1 s measured, nftables 1.0.6), on every run's teardown."""
        self.proc.kill()
        end_fed_process(self.proc)


def end_fed_process(proc: subprocess.Popen, timeout_s: float = 5.0) -> None:
    """A process fed on stdin ends at its input's end: close it and wait, then kill what did not end in time."""
    try:
        proc.stdin.close()
    except OSError:
        pass
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout_s)


@dataclass(frozen=True)
class Station:
    vehicle_id: str
    netns: str
    address: str
    port: str  # its bridge port's name in the air namespace


def quick_acks(station: Station) -> str:
    """The `ip -batch` line that has the station's TCP acknowledge every segment at once (the prefix route's
    `quickack`, ip-route(8)). Linux otherwise holds an acknowledgement up to TCP_DELACK_MIN, 40 ms of wall time
    (include/net/tcp.h; no sysctl sets it), which at a speed-up s is 40 s simulated ms: the job's and the probes'
    acknowledgements would come at other simulated times at every speed-up. Measured, `paper-flight-moving` four runs
    each at 1x and 4x: 4x / 1x pace 1.03 with this, 1.11 without (ten and seven runs); w1's probes at 6-8 m 1.02,
    against 1.38 (docs/benchmarks.md). On the HTB air too (a copy of paper-flight-static there, 60 s, 2-3 runs each
    at 1x and 4x, 2026-11-28: its probes 9.4-9.7 Mbit/s with it and without; that job is this host's CPU at any
    speed-up). A real station delays its acknowledgements; this one's cost is more of them on the air."""
    prefix = ipaddress.ip_interface(f"{station.address}/{AIR_PREFIX_LENGTH}").network
    return f"route replace {prefix} dev air0 src {station.address} quickack 1\n"


class AirNetwork:
    def __init__(self, vehicle_ids: list[str], ap: int | None, sharing: bool,
                 probe_ports: list[int | None] | None = None, speedup: float = 1.0,
                 congestion_control: str = "host"):
        if not 1 <= len(vehicle_ids) <= MAX_STATIONS:
            raise netns.NetworkError(f"a kernel network holds 1-{MAX_STATIONS} vehicles, not {len(vehicle_ids)}")
        self.speedup = speedup
        self.congestion_control = congestion_control  # "host" once create() finds the kernel cannot give it
        self.prefix = netns.new_prefix()
        tag = self.prefix.rsplit("-", 1)[1]
        self.air_ns = f"{self.prefix}-air"
        self.subnet_octet = 64 + int(tag, 16) % 64  # one /16 per run: nothing else on this host routes to it
        self.stations = [Station(v, f"{self.prefix}-{i}", f"10.{self.subnet_octet}.{(i + 1) // 256}.{(i + 1) % 256}",
                                 f"n{tag}p{i}") for i, v in enumerate(vehicle_ids)]
        self.layout = Layout(tuple(s.address for s in self.stations), tuple(s.port for s in self.stations),
                             tuple(probe_ports or [None] * len(vehicle_ids)), ap, sharing)
        self.air_tc: CommandStream | None = None
        self.ap_tc: CommandStream | None = None
        self.nft: CommandStream | None = None
        self.created: list[str] = []
        self._last_nft = ""

    @property
    def namespaces(self) -> list[str]:
        return [self.air_ns, *(s.netns for s in self.stations)]

    def create(self) -> AirNetwork:
        """Build everything, or remove what was built and raise NetworkError."""
        if self.congestion_control != "host" and not allow_congestion_control(self.congestion_control):
            self.congestion_control = "host"
        try:
            self._build()
        except Exception:
            self.close()
            raise
        return self

    def _add_namespaces(self) -> None:
        """Every namespace of self.namespaces, each remembered as made (close() deletes what was) before it is."""
        self.created += self.namespaces
        netns.run(["ip", "-batch", "-"], "creating the namespaces",
                  "".join(f"netns add {name}\n" for name in self.namespaces))

    def _build(self) -> None:
        self._add_namespaces()
        links = ["link add air type bridge", "link set air up", "link set lo up"]
        moves = []
        for s in self.stations:
            moves.append(f"link add {s.port} netns {self.air_ns} type veth peer name air0 netns {s.netns}")
            links += [f"link set {s.port} master air", f"link set {s.port} up"]
        netns.run(["ip", "-batch", "-"], "creating the veths", "\n".join(moves) + "\n")
        netns.run(["ip", "-n", self.air_ns, "-batch", "-"], "the bridge", "\n".join(links) + "\n")
        for s in self.stations:
            netns.run(["ip", "-n", s.netns, "-batch", "-"], f"{s.vehicle_id}'s interfaces",
                      f"link set lo up\naddr add {s.address}/{AIR_PREFIX_LENGTH} dev air0\nlink set air0 up\n"
                      f"{quick_acks(s)}")
            netns.run(["ip", "netns", "exec", s.netns, "sysctl", "-q", "-w", *self.tcp_settings()],
                      f"{s.vehicle_id}'s TCP settings")
        netns.run(["tc", "-n", self.air_ns, "-batch", "-"], "the air's qdiscs",
                  "\n".join(self.layout.air_setup()) + "\n")
        if self.layout.shared():
            netns.run(["tc", "-n", self.stations[self.layout.ap].netns, "-batch", "-"], "the access point's qdisc",
                      "\n".join(self.layout.ap_setup()) + "\n")
        netns.run(["ip", "netns", "exec", self.air_ns, "nft", "-f", "-"], "the loss table",
                  self.layout.nft_setup(NFT_TABLE))
        self.air_tc = CommandStream(["tc", "-n", self.air_ns, "-force", "-batch", "-"], "tc (air)")
        if self.layout.shared():
            self.ap_tc = CommandStream(["tc", "-n", self.stations[self.layout.ap].netns, "-force", "-batch", "-"],
                                       "tc (access point)")
        self.nft = CommandStream(["ip", "netns", "exec", self.air_ns, "nft", "-i"], "nft (air)")
        self.wait_for_carrier()

    def wait_for_carrier(self, timeout_s: float = CARRIER_TIMEOUT_S) -> None:
        """Every station's air0 running before anything uses it. On some kernels (6.18) the access point's air0
        loses its carrier when its root qdisc is attached and stays NO-CARRIER (operstate DOWN) until it is set
        up again; MPI's transport then finds no usable device. Set up again until each runs, within the timeout."""
        deadline = time.monotonic() + timeout_s
        waiting = [s for s in self.stations if not self._running(s)]
        while waiting:
            if time.monotonic() > deadline:
                names = ", ".join(s.vehicle_id for s in waiting)
                raise netns.NetworkError(f"{names}: air0 has no carrier {timeout_s:g} s after it was set up")
            for s in waiting:
                log.info("%s: air0 without a carrier; setting it up again", s.vehicle_id)
                netns.run(["ip", "-n", s.netns, "-batch", "-"], f"{s.vehicle_id}'s air0",
                          "link set air0 down\nlink set air0 up\n")
            time.sleep(CARRIER_POLL_S)
            waiting = [s for s in waiting if not self._running(s)]

    @staticmethod
    def _running(station: Station) -> bool:
        shown = netns.run(["ip", "-n", station.netns, "-j", "link", "show", "dev", "air0"],
                          f"{station.vehicle_id}'s air0")
        try:
            return json.loads(shown)[0].get("operstate") == "UP"
        except (ValueError, IndexError, AttributeError):
            return False

    def tcp_settings(self) -> list[str]:
        """TCP's timers on the simulator's clock: its retransmission timeouts (and their back-off after a link
        comes back into range) divided by the speed-up, as the links' rates are multiplied by it. Slow start
        is not restarted after idle: each iteration's transfer follows a pause, and restarting would cost
        round trips whose number does not scale. And the congestion control a scenario names for the companions."""
        rto_min_us = max(round(TCP_RTO_MIN_US / self.speedup), 1000)
        rto_max_ms = min(max(round(TCP_RTO_MAX_MS / self.speedup), 1000), TCP_RTO_MAX_MS)
        settings = ["net.ipv4.tcp_slow_start_after_idle=0", f"net.ipv4.tcp_rto_min_us={rto_min_us}",
                    f"net.ipv4.tcp_rto_max_ms={rto_max_ms}"]
        if self.congestion_control != "host":
            settings.insert(0, f"net.ipv4.tcp_congestion_control={self.congestion_control}")
        present = [item for item in settings if Path("/proc/sys", *item.split("=")[0].split(".")).exists()]
        if len(present) < len(settings):  # tcp_rto_max_ms came with Linux 6.15, tcp_rto_min_us a little before
            log.warning("this kernel cannot set %s: TCP's timers stay on the wall clock",
                        ", ".join(item.split("=")[0] for item in settings if item not in present))
        return present

    def apply(self, state: AirState, pace: float) -> None:
        """Every pair's rate and loss as the shaper computed them: HTB classes changed in place and, when it
        differs from the last, the nftables loss chain refilled."""
        self.air_tc.send("\n".join(self.layout.air_update(state, pace)))
        if self.ap_tc is not None:
            self.ap_tc.send("\n".join(self.layout.ap_update(state, pace)))
        nft = self.layout.nft_update(NFT_TABLE, state)
        if nft != self._last_nft:
            self.nft.send(nft)
            self._last_nft = nft

    def silence(self, index: int, silent: bool = True) -> None:
        """Station `index` neither sends nor hears any more (its companion lost its power): its air0 down; or,
        silent=False, up again (a rebooted companion: its address, and the prefix route the kernel re-adds)."""
        s = self.stations[index]
        netns.run(["ip", "-n", s.netns, "-batch", "-"], f"{s.vehicle_id}'s air0",
                  "link set air0 down\n" if silent else f"link set air0 up\n{quick_acks(s)}")

    def exec_prefix(self, index: int) -> list[str]:
        """The command prefix that runs a program on station `index`."""
        return ["ip", "netns", "exec", self.stations[index].netns]

    def close(self) -> None:
        for stream in (self.air_tc, self.ap_tc, self.nft):
            if stream is not None:
                stream.abandon()
        self.air_tc = self.ap_tc = self.nft = None
        for name in reversed(self.created):
            netns.delete_namespace(name)
        self.created = []
