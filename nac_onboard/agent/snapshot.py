"""What the agent knows at one moment: its own vehicle and every peer heard, typed.

The agent takes a snapshot for each state-feed answer and each throughput probe; only the state feed
(nac_onboard.agent.state_feed) turns it into JSON, for the processes that ask. Pure: no sockets or clocks here.
"""

from __future__ import annotations

from dataclasses import dataclass

from missions.geo import distance_m
from nac_onboard.agent.peers import HeardPeer, PeerState


@dataclass(frozen=True)
class OwnState:
    """This vehicle as its autopilot reports it (None: not known yet)."""

    id: str
    role: str
    sysid: int
    lat_deg: float | None
    lon_deg: float | None
    alt_m: float | None  # AMSL
    vel_ned_mps: tuple[float, float, float] | None
    battery_pct: int | None
    mpi_build: str
    link_up: bool  # the autopilot link: a position from a lost link is its last one

    @classmethod
    def of(cls, state: PeerState, link_up: bool) -> OwnState:
        """From the peer message this vehicle broadcasts about itself."""
        return cls(id=state.id, role=state.role, sysid=state.sysid, lat_deg=state.lat_deg, lon_deg=state.lon_deg,
                   alt_m=state.alt_m, vel_ned_mps=state.vel_ned_mps, battery_pct=state.battery_pct,
                   mpi_build=state.mpi_build, link_up=link_up)


@dataclass(frozen=True)
class ProbeResult:
    """The latest probe from this vehicle to one peer: what the MPI master may plan its blocks by in flight."""

    peer: str
    bits_per_second: float  # 0.0: the probe failed (out of range, refused, timed out)
    age_s: float  # wall seconds since it ended


@dataclass(frozen=True)
class AgentSnapshot:
    t_s: float  # unix time when it was taken
    own: OwnState  # "self" in the state feed's answer
    peers: tuple[HeardPeer, ...] = ()  # every peer in the table, lost ones included, in the table's order
    probes: tuple[ProbeResult, ...] = ()  # this vehicle's latest throughput probe to each peer it probes

    def vehicle(self, vehicle_id: str) -> OwnState | PeerState | None:
        """This vehicle or a peer (its last message) by id; None if unknown."""
        if self.own.id == vehicle_id:
            return self.own
        return next((p.state for p in self.peers if p.state.id == vehicle_id), None)

    def distance_m(self, a: str, b: str) -> float | None:
        """Straight-line distance between two vehicles; None when either position is unknown."""
        va, vb = self.vehicle(a), self.vehicle(b)
        return None if va is None or vb is None else distance_m(position(va), position(vb))


def position(vehicle: OwnState | PeerState) -> dict:
    """{lat_deg, lon_deg, alt_m} of a vehicle, each None while unknown."""
    return {"lat_deg": vehicle.lat_deg, "lon_deg": vehicle.lon_deg, "alt_m": vehicle.alt_m}
