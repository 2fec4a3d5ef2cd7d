"""Linux network namespaces as the simulated companions' hosts: the checks before a kernel network starts, the
commands that build and remove one, sockets opened inside a namespace, and the cleanup of what a killed run left.

Every namespace a run creates is named `nacnet-<pid>-<tag>-...` after the process that owns it, so a later run
finds leftovers (an owner that no longer exists) and removes them, and parallel runs never share a name. A run
killed with SIGKILL has its namespaces removed at once by its watchdog (sitl/experiment/watchdog.py, which calls
delete_namespace); remove_leftovers is for what even that missed (the watchdog killed as well).
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import re
import secrets
import shutil
import socket
import subprocess
import threading
import time

from nac_onboard.compute.launch import kill_leaving_nothing
from nac_onboard.errors import BadInput, OperationFailed

log = logging.getLogger(__name__)
PREFIX = "nacnet-"
NETNS_DIR = "/run/netns"
CLONE_NEWNET = 0x40000000
COMMAND_TIMEOUT_S = 20.0
TOOLS = ("ip", "tc", "nft")


class NetworkUnavailable(BadInput):
    """A kernel network cannot run here (privileges, tools, kernel support): the message says what is missing."""


class NetworkError(OperationFailed):
    """A network command failed while the run was being set up or shaped."""


def run(command: list[str], what: str, stdin: str | None = None, timeout_s: float = COMMAND_TIMEOUT_S) -> str:
    try:
        done = subprocess.run(command, input=stdin, capture_output=True, text=True, timeout=timeout_s)
    except FileNotFoundError:
        raise NetworkError(f"{what}: {command[0]} is not installed") from None
    except subprocess.TimeoutExpired:
        raise NetworkError(f"{what}: `{' '.join(command[:6])}` did not finish within {timeout_s:g} s") from None
    if done.returncode != 0:
        raise NetworkError(f"{what}: `{' '.join(command[:6])}` exited {done.returncode}: "
                           f"{done.stderr.strip()[-500:]}")
    return done.stdout


def new_prefix() -> str:
    """A run's namespace prefix: its owner's pid, and a tag so two runs of one process differ too."""
    return f"{PREFIX}{os.getpid()}-{secrets.token_hex(2)}"


def check_kernel_network() -> None:
    """Raise NetworkUnavailable, with one sentence naming what is missing, unless this process can build a kernel
    network: root, ip/tc/nft, and a trial namespace with a bridge, a veth, an HTB qdisc and an nftables table."""
    if os.geteuid() != 0:
        raise NetworkUnavailable("--network kernel needs root (network namespaces, tc and nftables); run as root "
                                 "or use --network sleep")
    missing = [tool for tool in TOOLS if shutil.which(tool) is None]
    if missing:
        raise NetworkUnavailable(f"--network kernel needs {', '.join(missing)} (Debian: apt-get install iproute2 "
                                 "nftables); or use --network sleep")
    trial = f"{new_prefix()}-trial"
    try:
        run(["ip", "netns", "add", trial], "a trial network namespace", timeout_s=5.0)
        for what, command, stdin in [
            ("a bridge and a veth", ["ip", "-n", trial, "-batch", "-"],
             "link add nacbr type bridge\nlink add nacva type veth peer name nacvb\n"),
            ("an HTB qdisc", ["tc", "-n", trial, "qdisc", "add", "dev", "nacva", "root", "handle", "1:", "htb"],
             None),
            ("an nftables bridge table", ["ip", "netns", "exec", trial, "nft", "-f", "-"],
             "table bridge nactrial { chain loss { type filter hook forward priority 0; }; }\n"),
        ]:
            run(command, what, stdin, timeout_s=5.0)
    except NetworkError as err:
        raise NetworkUnavailable(f"--network kernel cannot build its network here ({err}); use --network sleep") \
            from None
    finally:
        delete_namespace(trial)


def namespaces() -> list[str]:
    try:
        return sorted(os.listdir(NETNS_DIR))
    except OSError:
        return []


def _owner_alive(name: str) -> bool:
    match = re.match(rf"{PREFIX}(\d+)-", name)
    if not match:
        return True  # not ours
    try:
        os.kill(int(match.group(1)), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_leftovers() -> list[str]:
    """Namespaces of runs whose process is gone: their processes killed and the namespaces (with their links,
    qdiscs and nftables tables) removed. Returns their names."""
    gone = [name for name in namespaces() if name.startswith(PREFIX) and not _owner_alive(name)]
    for name in gone:
        log.warning("removing network namespace %s, left by a run that no longer exists", name)
        delete_namespace(name)
    return gone


def pids_in(name: str) -> list[int]:
    try:
        out = subprocess.run(["ip", "netns", "pids", name], capture_output=True, text=True, timeout=5.0).stdout
    except (OSError, subprocess.TimeoutExpired):
        return []
    return [int(p) for p in out.split() if p.isdigit()]


def forget_connections(name: str) -> None:
    """Every TCP socket of the namespace destroyed (SOCK_DESTROY, `ss -K`): what a companion's reboot does to its
    connections, which its killed processes' sockets would otherwise outlive (closing, retransmitting their FIN)."""
    with contextlib.suppress(OSError, subprocess.TimeoutExpired):
        subprocess.run(["ip", "netns", "exec", name, "ss", "-K", "-t", "state", "all"], capture_output=True,
                       timeout=COMMAND_TIMEOUT_S)


def delete_namespace(name: str) -> None:
    """Kill what runs inside, then delete the namespace: its veth ends, bridge, qdiscs and tables go with it."""
    kill_leaving_nothing(pids_in(name))
    with contextlib.suppress(OSError, subprocess.TimeoutExpired):
        subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=10.0)


def socket_in_netns(name: str, family: int, kind: int) -> socket.socket:
    """A socket that belongs to network namespace `name` (it keeps it for life)."""
    return in_netns(name, lambda: socket.socket(family, kind))


def udp_echo_round_trips(client_ns: str, server_ns: str, server_address: str, count: int, gap_s: float,
                         timeout_s: float, server_thread: bool = False) -> list[float]:
    """Round trips (wall seconds) of a 100-byte UDP echo from namespace client_ns to server_address in server_ns,
    gap_s apart, both ends in this thread or (server_thread) the server in a thread of its own; OSError (a
    TimeoutError) when one is not back within timeout_s."""
    server = socket_in_netns(server_ns, socket.AF_INET, socket.SOCK_DGRAM)
    client = socket_in_netns(client_ns, socket.AF_INET, socket.SOCK_DGRAM)
    try:
        server.bind((server_address, 0))
        for end in (server, client):
            end.settimeout(timeout_s)
        serving = threading.Thread(target=_echo_back, args=(server, count), daemon=True) if server_thread else None
        if serving is not None:
            serving.start()
        round_trips = []
        for _ in range(count):
            start = time.perf_counter()
            client.sendto(b"x" * 100, server.getsockname())
            if serving is None:
                _echo_back(server, 1)
            client.recvfrom(2048)
            round_trips.append(time.perf_counter() - start)
            time.sleep(gap_s)
        return round_trips
    finally:
        server.close()
        client.close()


def _echo_back(server: socket.socket, count: int) -> None:
    for _ in range(count):
        try:
            message, sender = server.recvfrom(2048)
            server.sendto(message, sender)
        except OSError:  # the client gave up and closed both ends
            return


def in_netns(name: str, make):
    """make() called by a short-lived thread that enters network namespace `name`, the rest of this process
    staying where it is: what it opens (a socket, a TUN device) belongs to that namespace for life."""
    result: dict = {}

    def enter_and_make() -> None:
        libc = ctypes.CDLL(None, use_errno=True)
        try:
            fd = os.open(os.path.join(NETNS_DIR, name), os.O_RDONLY)
        except OSError as err:
            result["error"] = NetworkError(f"network namespace {name}: {err.strerror}")
            return
        try:
            if libc.setns(fd, CLONE_NEWNET) != 0:
                result["error"] = NetworkError(f"cannot enter network namespace {name}: "
                                               f"{os.strerror(ctypes.get_errno())}")
                return
            result["made"] = make()
        except OSError as err:
            result["error"] = NetworkError(f"network namespace {name}: {err}")
        finally:
            os.close(fd)

    thread = threading.Thread(target=enter_and_make, name=f"netns-{name}")
    thread.start()
    thread.join()
    if "error" in result:
        raise result["error"]
    return result["made"]
