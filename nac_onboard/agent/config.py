"""The agent's configuration: a TOML file (deploy/*.toml) loaded into frozen dataclasses, checked at the edge.

Every key has a default except the vehicle's id and role; an unknown key or a value of the wrong type is an error
that names the file, the key and what was expected (a typo must not silently fall back to a default).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from nac_onboard.address import is_loopback, parse_host_port
from nac_onboard.agent.peers import FleetKey
from nac_onboard.errors import BadInput
from nac_onboard.inputs import check_id, check_name, check_number
from nac_onboard.mavlink.signing import load_signing_key
from nac_onboard.radio.channel import ChannelModel
from nac_onboard.radio.files import load_channel
from nac_onboard.records import kinds
from nac_onboard.tomlfile import read_toml, to_dataclass

ROLES = ("master", "worker")
MIN_PASSPHRASE_CHARS = 16  # a fleet key file's passphrase (a file of 64 hex characters is the key itself)
PROBE_TOOLS = ("nac", "iperf3")


class ConfigError(BadInput):
    """The configuration file is unusable; the message names the file, the key and what was expected."""


@dataclass(frozen=True)
class VehicleSection:
    id: str
    role: str
    sysid: int = 0  # the autopilot's system id; 0 = the first autopilot heard


@dataclass(frozen=True)
class AutopilotSection:
    uri: str = "serial:/dev/ttyTHS2:921600"  # Jetson TX2 TELEM2; SITL: udpin:127.0.0.1:<companion port>
    # a listening link (udpin:, tcpin:) takes one peer: this IPv4 "HOST:PORT" or "HOST" (any port of it); "" = the
    # first sender that speaks valid MAVLink, then locked. Everyone else is refused and counted (docs/security.md)
    peer: str = ""
    link_timeout_s: float = 3.0  # no heartbeat this long = link lost
    reconnect_s: float = 2.0  # how often a lost serial/tcp link is reopened
    stream_hz: float = 10.0  # telemetry rate asked of the autopilot (REQUEST_DATA_STREAM); 0 = leave as is
    signing_key_file: str = ""


@dataclass(frozen=True)
class LogSection:
    dir: str = "/var/log/nac"
    run_id: str = ""  # "" = $NAC_RUN_ID or the start time (UTC)
    telemetry_hz: float = 10.0
    tlog: bool = True
    fsync_s: float = 1.0  # how often logs are forced to disk (0 = never; the kernel still has every record)


@dataclass(frozen=True)
class RoutingSection:
    endpoints: tuple[str, ...] = ()  # MAVLink endpoints sharing the autopilot link (MAVProxy, tools): may command
    watch: tuple[str, ...] = ()  # read-only endpoints: telemetry out, nothing they send reaches the autopilot
    allow: tuple[str, ...] = ()  # HOST:PORT senders a udpin endpoint also accepts (besides the first that spoke)


@dataclass(frozen=True)
class PeersSection:
    listen: str = "0.0.0.0:47100"
    send_to: tuple[str, ...] = ("255.255.255.255:47100",)
    rate_hz: float = 2.0
    timeout_s: float = 3.0  # silent this long: peer_lost
    forget_s: float = 60.0  # silent this long: out of the table
    max_peers: int = 64  # new ids beyond this are refused and counted
    key_file: str = ""  # the fleet key, the same on every vehicle (docs/security.md); relative: beside this file
    key_id: str = "fleet"  # names the key in each message, so a fleet can change keys
    allow_unsigned: bool = False  # accept peers that do not sign (a lab without keys, at its own risk)
    # a peer's new boot (or one first heard since our start) dated further from our clock is refused (needs clocks
    # synced to within it); later messages of that boot are judged by the sender's own sequence (docs/security.md)
    replay_window_s: float = 30.0
    # the last sequence accepted from each peer, so our restart does not accept datagrams captured before it;
    # "" = $STATE_DIRECTORY (systemd's, /var/lib/nac) or else log.dir, as peer-freshness-VEHICLE.json
    state_file: str = ""


@dataclass(frozen=True)
class StateFeedSection:
    listen: str = "127.0.0.1:47200"  # where the local compute job asks for positions
    expose: bool = False  # must be true to listen beyond loopback: anyone who can reach it learns where we all are


@dataclass(frozen=True)
class ThroughputSection:
    server: bool = True
    bind: str = "0.0.0.0"
    port: int = 5201
    probe: bool = False  # the master probes; workers only serve
    period_s: float = 10.0  # one round of probes (every target once) starts every period_s
    # true: one schedule per target, all at once (one iperf3 client per link: a probe that stalls holds up no other
    # link's, and each link is measured over the same seconds); false: the targets in turn, round by round
    concurrent: bool = False
    duration_s: float = 1.0
    bytes: int = 0  # > 0: send this many bytes instead of for duration_s
    interval_s: float = 0.5
    rate_bps: float = 0.0  # cap on the probe's sending rate; 0 = as fast as the path allows
    targets: tuple[str, ...] = ()  # "id=host:port"; empty = every worker in the peer table
    # SITL only: a channel preset or TOML; each probe is then paced at the model's capacity for the pair's distance
    # (and fails below its minimum rate), so loopback behaves like the radio. "" = measure the real network.
    emulate_channel: str = ""
    # the probes begin once this file exists ("" = at once). SITL gives its run's go, which the MPI job waits for
    # too: the probes measure the flight the job computes in, and leave the job's set-up the air
    start_file: str = ""
    # "nac": our probe, against `nac-onboard throughput server`; "iperf3": `iperf3 --client --json` against an
    # `iperf3 --server` on each target (run it there yourself; SITL's runner does), whole seconds per probe
    tool: str = "nac"

    @property
    def duty_cycle(self) -> float:
        """Share of the time one target's path carries probe traffic (when probing by duration)."""
        return self.duration_s / self.period_s if self.period_s > 0 else 1.0


@dataclass(frozen=True)
class AgentConfig:
    vehicle: VehicleSection
    autopilot: AutopilotSection = field(default_factory=AutopilotSection)
    log: LogSection = field(default_factory=LogSection)
    routing: RoutingSection = field(default_factory=RoutingSection)
    peers: PeersSection = field(default_factory=PeersSection)
    state_feed: StateFeedSection = field(default_factory=StateFeedSection)
    throughput: ThroughputSection = field(default_factory=ThroughputSection)
    source: str = "<config>"
    emulated_channel: ChannelModel | None = None  # throughput.emulate_channel, loaded
    fleet_key: FleetKey | None = None  # peers.key_file, loaded


SECTIONS = {"vehicle": VehicleSection, "autopilot": AutopilotSection, "log": LogSection,
            "routing": RoutingSection, "peers": PeersSection, "state_feed": StateFeedSection,
            "throughput": ThroughputSection}


def parse_agent_config(data: dict, source: str = "<config>") -> AgentConfig:
    unknown = set(data) - set(SECTIONS)
    if unknown:
        raise ConfigError(f"{source}: unknown section [{sorted(unknown)[0]}] (known: {', '.join(SECTIONS)})")
    if "vehicle" not in data:
        raise ConfigError(f"{source}: missing [vehicle] with id and role")
    sections = {name: to_dataclass(cls, data[name], source, ConfigError, table=name)
                for name, cls in SECTIONS.items() if name in data}
    config = AgentConfig(source=source, **sections)
    _check(config)
    if config.peers.key_file:
        key_path = Path(config.peers.key_file)
        if not key_path.is_absolute() and source != "<config>":
            key_path = Path(source).parent / key_path  # beside the config file, as install.sh puts it
        try:
            _check_fleet_passphrase(key_path)
            secret = load_signing_key(key_path)
            config = dataclasses.replace(config, fleet_key=FleetKey(config.peers.key_id, secret))
        except BadInput as err:
            raise ConfigError(f"{source}: peers.key_file: {err}") from None
    if config.throughput.emulate_channel:  # loaded here, once, and handed to the probes
        try:
            channel = load_channel(config.throughput.emulate_channel)
        except BadInput as err:
            raise ConfigError(f"{source}: throughput.emulate_channel: {err}") from None
        config = dataclasses.replace(config, emulated_channel=channel)
    return config


def _check(c: AgentConfig) -> None:
    src = c.source
    if c.vehicle.role not in ROLES:
        raise ConfigError(f"{src}: vehicle.role must be one of {', '.join(ROLES)}, got {c.vehicle.role!r}")
    check_id(c.vehicle.id, f"{src}: vehicle.id", ConfigError)
    if c.log.run_id:
        check_name(c.log.run_id, f"{src}: log.run_id (a directory name; \"\" for the start time)", ConfigError)
    positive = {"autopilot.link_timeout_s": c.autopilot.link_timeout_s, "autopilot.reconnect_s":
                c.autopilot.reconnect_s, "log.telemetry_hz": c.log.telemetry_hz, "peers.rate_hz": c.peers.rate_hz,
                "peers.timeout_s": c.peers.timeout_s, "peers.forget_s": c.peers.forget_s,
                "peers.max_peers": c.peers.max_peers, "peers.replay_window_s": c.peers.replay_window_s,
                "throughput.period_s": c.throughput.period_s,
                "throughput.duration_s": c.throughput.duration_s, "throughput.interval_s": c.throughput.interval_s}
    for key, value in positive.items():
        if not value > 0:
            raise ConfigError(f"{src}: {key} must be > 0, got {value}")
    _check_ranges(c)
    if c.throughput.interval_s < 0.05:
        raise ConfigError(f"{src}: throughput.interval_s must be >= 0.05 s (servers refuse finer intervals)")
    if not c.peers.key_file and not c.peers.allow_unsigned:
        raise ConfigError(f"{src}: peers.key_file is not set: give the fleet key file (docs/security.md), or set "
                          "peers.allow_unsigned = true to accept peer state that anyone on the network can forge")
    t = c.throughput
    if t.tool not in PROBE_TOOLS:
        raise ConfigError(f"{src}: throughput.tool must be one of {', '.join(PROBE_TOOLS)}, got {t.tool!r}")
    if t.tool == "iperf3" and (t.emulate_channel or t.bytes or t.rate_bps):
        raise ConfigError(f"{src}: throughput.tool = \"iperf3\" measures the path as it is: it cannot be paced "
                          "(emulate_channel, rate_bps) nor sized (bytes)")
    if t.probe and t.tool == "iperf3" and shutil.which("iperf3") is None:
        raise ConfigError(f"{src}: throughput.tool = \"iperf3\" but iperf3 is not installed")
    if t.probe and t.bytes == 0 and t.duration_s > t.period_s:
        raise ConfigError(f"{src}: throughput.duration_s ({t.duration_s}) exceeds throughput.period_s "
                          f"({t.period_s}): the probe would never pause for other traffic")
    try:
        from nac_onboard.mavlink.client import mavutil_device  # the URI table lives with the MAVLink adapter

        for uri in (c.autopilot.uri, *c.routing.endpoints, *c.routing.watch):
            mavutil_device(uri)
        _check_autopilot_peer(c.autopilot)
        for text in c.routing.allow:
            parse_host_port(text, "routing.allow")
        for key, text in [("peers.listen", c.peers.listen), ("state_feed.listen", c.state_feed.listen)]:
            parse_host_port(text, key, allow_port_zero=True)
        feed_host, _ = parse_host_port(c.state_feed.listen, "state_feed.listen", allow_port_zero=True)
        if not is_loopback(feed_host) and not c.state_feed.expose:
            raise BadInput(f"state_feed.listen {c.state_feed.listen} is beyond loopback: anyone who reaches it learns "
                           "every vehicle's position; set state_feed.expose = true if that is meant")
        for text in c.peers.send_to:
            parse_host_port(text, "peers.send_to")
        for target in t.targets:
            name, eq, address = target.partition("=")
            if not eq or not name:
                raise BadInput(f"throughput.targets: expected ID=HOST:PORT, got {target!r}")
            parse_host_port(address, "throughput.targets")
    except BadInput as err:
        raise ConfigError(f"{src}: {err}") from None


def _check_autopilot_peer(a: AutopilotSection) -> None:
    """autopilot.peer names who may be the autopilot on a listening link; the other schemes have one peer by
    construction (the device, the address connected to), where a peer setting would be a misunderstanding."""
    from nac_onboard.mavlink.client import parse_peer

    parse_peer(a.peer, "autopilot.peer")
    scheme = a.uri.partition(":")[0]
    if a.peer and scheme not in ("udpin", "tcpin"):
        raise BadInput(f"autopilot.peer is only for a listening link (udpin:, tcpin:); {a.uri} has one peer by "
                       "construction: remove autopilot.peer")


#: numeric keys with the range they must lie in (low, high[, unit]): checked before anything starts, so a value a
#: MAVLink field or a socket cannot carry is refused naming the key instead of failing when the link comes up
RANGES = {
    "vehicle.sysid": (0, 255, "(0: the first autopilot heard)"), "autopilot.link_timeout_s": (0.1, 3600, "s"),
    "autopilot.reconnect_s": (0.1, 3600, "s"), "autopilot.stream_hz": (0, 1000, "Hz (0: leave as is)"),
    "log.telemetry_hz": (0.01, 1000, "Hz"), "log.fsync_s": (0, 86400, "s (0: never)"),
    "peers.rate_hz": (0.01, 1000, "Hz"), "peers.timeout_s": (0.1, 86400, "s"), "peers.forget_s": (0.1, 86400, "s"),
    "peers.max_peers": (1, 100_000, "peers"), "peers.replay_window_s": (0.1, 86400, "s"),
    "throughput.port": (1, 65535, ""), "throughput.period_s": (0.05, 86400, "s"),
    "throughput.duration_s": (0.05, 3600, "s"), "throughput.bytes": (0, 2**40, "bytes (0: by duration)"),
    "throughput.interval_s": (0.05, 3600, "s"), "throughput.rate_bps": (0, 1e12, "bit/s (0: no cap)"),
}


def _check_ranges(c: AgentConfig) -> None:
    for key, (low, high, unit) in RANGES.items():
        section, _, name = key.partition(".")
        value = getattr(getattr(c, section), name)
        check_number(value, f"{c.source}: {key}", low, high, integer=isinstance(value, int), unit=unit,
                     error=ConfigError)


def _check_fleet_passphrase(path: Path) -> None:
    """A fleet key file holds 64 hex characters (the secret) or a passphrase whose SHA-256 is the secret: anyone who
    guesses a short passphrase can sign peer state for the whole fleet, so one under MIN_PASSPHRASE_CHARS is refused."""
    try:
        if not path.is_file():
            return  # load_signing_key names what is wrong with it
        with open(path, "rb") as f:
            text = f.read(4096).decode().strip()
    except (OSError, UnicodeDecodeError):
        return
    if len(text) == 64 and all(ch in "0123456789abcdefABCDEF" for ch in text):
        return  # the 32-byte key itself
    if len(text) < MIN_PASSPHRASE_CHARS:
        raise BadInput(f"{path}: a passphrase of {len(text)} characters is too weak: at least {MIN_PASSPHRASE_CHARS} "
                       "characters, or 64 hex characters (a 32-byte key, docs/security.md)")


def peers_state_path(config: AgentConfig) -> Path:
    """Where the agent keeps the last sequence accepted from each peer (peers.state_file)."""
    if config.peers.state_file:
        return Path(config.peers.state_file)
    directory = os.environ.get("STATE_DIRECTORY", "").split(":")[0] or config.log.dir
    return Path(directory) / kinds.PEER_FRESHNESS.file_name(config.vehicle.id)


def load_agent_config(path: str | Path) -> AgentConfig:
    return parse_agent_config(read_toml(path, "agent config", ConfigError), str(path))
