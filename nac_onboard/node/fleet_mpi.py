"""An MPI job over the vehicles the master's agent hears: the hostfile in rank order (the master, then the live
workers) and the check that every node runs the same MPI build, naming the odd one out. Pure: the state comes
from the agent's state feed."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from nac_onboard.agent.state_feed import StateFeedError, fetch_state
from nac_onboard.errors import BadInput, OperationFailed
from nac_onboard.node.mpi_build import UNKNOWN_PREFIX


@dataclass(frozen=True)
class Node:
    id: str
    role: str
    host: str
    mpi_build: str


class MpiBuildMismatch(BadInput):
    """Nodes that would be ranks of one job run different MPI builds (or none)."""


def job_nodes(state: dict, master_host: str) -> tuple[list[Node], list[str]]:
    """The nodes of a job in rank order, this master first and then the live workers by id, and one note per
    peer left out (lost, another master, no address)."""
    me = state.get("self") or {}
    if me.get("role") != "master":
        raise BadInput(f"this agent ({me.get('id', '?')}) is a {me.get('role', '?')}: run this on the master, rank 0")
    nodes = [Node(me["id"], "master", master_host, me.get("mpi_build") or "")]
    notes = []
    for peer_id, peer in sorted((state.get("peers") or {}).items()):
        if peer.get("lost"):
            notes.append(f"{peer_id}: lost (last heard {peer.get('age_s', '?')} s ago), left out")
        elif peer.get("role") != "worker":
            notes.append(f"{peer_id}: a {peer.get('role')}, not a worker, left out")
        elif not peer.get("host"):
            notes.append(f"{peer_id}: no address heard, left out")
        else:
            nodes.append(Node(peer_id, "worker", peer["host"], peer.get("mpi_build") or ""))
    if len(nodes) < 2:
        raise OperationFailed("no live worker heard: an MPI job needs the master and at least one worker"
                              + (f" ({'; '.join(notes)})" if notes else ""))
    return nodes, notes


def heard_workers(state: dict) -> dict[str, str]:
    """The workers the agent hears now (not lost): id -> the boot of its agent (another boot: it restarted)."""
    return {peer_id: str(peer.get("boot", "")) for peer_id, peer in (state.get("peers") or {}).items()
            if isinstance(peer, dict) and not peer.get("lost") and peer.get("role") == "worker"}


def workers_heard_at(feed: str, timeout_s: float, sock=None) -> dict[str, str] | None:
    """heard_workers from the agent's state feed at `feed` (host:port), None if it does not answer: what the job's
    supervisor asks (nac_onboard.compute.supervisor)."""
    try:
        return heard_workers(fetch_state(feed, timeout_s, sock=sock))
    except StateFeedError:
        return None


def check_builds(nodes: list[Node]) -> str:
    """The build every node runs, or MpiBuildMismatch naming each node that differs from the most common one
    (the master's on a tie) or reports none."""
    reported = [n for n in nodes if n.mpi_build and not n.mpi_build.startswith(UNKNOWN_PREFIX)]
    counts = Counter(n.mpi_build for n in reported)
    master_build = nodes[0].mpi_build
    common = max(counts, key=lambda b: (counts[b], b == master_build)) if counts else ""
    odd = []
    for n in nodes:
        if not n.mpi_build:
            odd.append(f"{n.id} ({n.host}) reports no MPI build (its agent predates the check, or has not "
                       "been heard since it started)")
        elif n.mpi_build.startswith(UNKNOWN_PREFIX):
            odd.append(f"{n.id} ({n.host}) has no usable MPI: {n.mpi_build.removeprefix(UNKNOWN_PREFIX)}")
        elif n.mpi_build != common:
            odd.append(f"{n.id} ({n.host}) runs {n.mpi_build!r}")
    if odd:
        others = counts[common]
        raise MpiBuildMismatch(f"every rank needs the same MPI build; {others} of {len(nodes)} nodes run "
                               f"{common!r}, but " + "; ".join(odd))
    return common


def hostfile_text(nodes: list[Node]) -> str:
    """MPICH's hostfile (`mpiexec -f`): one rank per vehicle, rank 0 the master."""
    lines = ["# MPICH hostfile written by `nac-onboard mpi hostfile`: rank 0 the master, then the workers by id"]
    for rank, n in enumerate(nodes):
        lines += [f"# rank {rank}: {n.id} ({n.role}, {n.mpi_build})", f"{n.host}:1"]
    return "\n".join(lines) + "\n"

